"""groom batch / groomtool.batch: Dask local clusters of 2 worker processes, a corrupt input, a killed
worker, resume, and output sets that are never half-written."""

from __future__ import annotations

import csv
import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from groomtool import batch  # noqa: E402
from groomtool.cli.main import main  # noqa: E402
from groomtool.examples import example_groom  # noqa: E402
from groomtool.groom import GroomError  # noqa: E402
from groomtool.invert import InversionParams  # noqa: E402
from groomtool.io import save_groom  # noqa: E402

PARAMS = {"contacts": "head", "contact_radius": 5e-4}  # the example's strands lie 0.24 mm above its head
NAMES = ("g0", "g1", "g2")


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """Three tiny grooms (3 strands each) on the example head, and a corrupt one."""
    d = tmp_path_factory.mktemp("batch_inputs")
    for seed, name in enumerate(NAMES):
        groom, head = example_groom(n_strands=3, seed=seed)
        save_groom(groom, d / f"{name}.obj")
    head.export(d / "head.obj")
    (d / "broken.obj").write_text("v 0 0 0\nv 0 -0.01 0\nv nan 0 0\nl 1 2 3\n")
    return d


@pytest.fixture(scope="module")
def client():
    """The batch's own local cluster (2 processes, 1 thread each), shared by the tests of this module."""
    saved = {k: os.environ.get(k) for k in batch.THREAD_ENV}
    with batch._local_cluster(2, "auto", 3) as cluster, distributed.Client(cluster) as c:
        yield c
    batch._restore_environ(saved)  # the nanny wrote its pre-spawn environment into this process


def inputs(data, names=NAMES):
    return [data / f"{n}.obj" for n in names]


def assert_nothing_half_written(out: Path):
    """Every groom directory is a complete output set; no staging directory, no temporary file."""
    for d in out.iterdir():
        assert not d.name.startswith("."), f"left behind: {d}"
        if d.is_dir():
            assert sorted(p.name for p in d.iterdir()) == ["fitted.obj", "report.json", "rest.npz",
                                                            "rest_shape.obj"], d
    assert not [p for p in out.rglob(".*") if p.is_file()], "temporary files left behind"


def allowed_failures(client, n):
    """Dask's retry budget (allowed-failures) on the shared cluster's scheduler."""
    def set_it(dask_scheduler):
        dask_scheduler.allowed_failures = n
    client.run_on_scheduler(set_it)


def read_csv(out: Path) -> dict:
    with open(out / "batch_summary.csv", newline="") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def test_cli_corrupt_input_is_reported_and_the_batch_completes(data, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["batch", *map(str, inputs(data)), str(data / "broken.obj"), "--head", str(data / "head.obj"),
            "--contacts", "head", "--contact-radius", "5e-4", "-o", str(out), "--workers", "2", "--quiet"]
    before = {k: os.environ.get(k) for k in batch.THREAD_ENV}
    assert main(argv) == 1  # an input error
    # the caller's environment is as it was (distributed's nanny sets NUMBA_NUM_THREADS=1 in the parent: left
    # there, the next numba compilation in this process would fail)
    assert {k: os.environ.get(k) for k in batch.THREAD_ENV} == before
    err = capsys.readouterr().err
    assert "broken: input_error" in err and str(data / "broken.obj") in err
    rows = read_csv(out)
    assert list(rows) == [*NAMES, "broken"]  # input order
    assert rows["broken"]["status"] == "input_error"
    assert str(data / "broken.obj") in rows["broken"]["error"] and "nan" in rows["broken"]["error"].lower()
    for name in NAMES:
        r = rows[name]
        report = json.loads((out / name / "report.json").read_text())
        assert r["status"] == "ok" and r["error"] == ""
        assert int(r["strands"]) == report["strands"] == 3
        assert int(r["contacts"]) == report["contacts"]["total"] > 0
        assert r["solve_status"] == report["solve"]["status"]
        assert float(r["residual"]) == pytest.approx(report["solve"]["residual"], rel=1e-5, abs=1e-300)
        assert int(r["unstable_strands"]) == report["stability"]["unstable_strands"]
        assert r["q0_error_bound"] == batch._cell(report["solve"].get("q0_error_bound"))
        assert float(r["wall_s"]) >= float(r["invert_s"]) > 0
        with np.load(out / name / "rest.npz") as z:
            q0 = np.linalg.norm(z["rest_curvatures"], axis=1).max()
        assert float(r["q0_max"]) == pytest.approx(q0, rel=1e-5)
    assert not (out / "broken").exists()
    assert_nothing_half_written(out)
    summary = json.loads((out / "batch_summary.json").read_text())
    assert summary["exit_code"] == 1
    assert summary["counts"]["ok"] == 3 and summary["counts"]["input_error"] == 1
    assert len(summary["grooms"]) == 4


def test_workers_run_one_thread(client):
    env = client.run(lambda: {k: os.environ.get(k) for k in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS",
                                                             "OPENBLAS_NUM_THREADS")})
    assert len(env) == 2
    assert all(v == {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
               for v in env.values())


def test_local_workers_fork_from_a_preloaded_server(client):
    """The local workers fork from multiprocessing's forkserver, which imported groomtool and ran the warm-up
    (the kernels an inversion uses, loaded) before the first task: none of it is paid in the first task,
    nor once per worker."""
    def state():
        import sys

        import groomtool.rods.superhelix as superhelix
        from groomtool.warmup import _dispatchers

        return {"invert": "groomtool.invert" in sys.modules,
                "warmed": "groomtool.examples" in sys.modules,  # imported by warm_up only, never by a task
                "kernels": sum(len(d.overloads) for d in _dispatchers(superhelix)),
                "parent": os.getppid(), "preload_env": os.environ.get(batch.PRELOAD_ENV)}

    got = client.run(state)
    assert len(got) == 2
    for s in got.values():
        assert s["invert"] and s["warmed"] and s["kernels"] > 0, s
        assert s["parent"] != os.getpid()  # forked by the server, not spawned by this process's nannies
        assert s["preload_env"] is None
    assert batch.PRELOAD_ENV not in os.environ


def test_the_forkserver_preload_loads_the_head_and_never_raises(data, monkeypatch):
    """What the forkserver runs when it imports groomtool.batch (in process here): the warm-up and the head,
    into the cache the tasks read; the spec is taken out of the environment; a bad spec costs nothing."""
    from groomtool.api import inversion_params

    monkeypatch.setattr(batch, "_HEADS", {})
    spec = {"head": str(data / "head.obj"), "units": "m", "params": None}
    import base64
    import pickle

    spec["params"] = base64.b64encode(pickle.dumps(inversion_params(**PARAMS))).decode("ascii")
    monkeypatch.setenv(batch.PRELOAD_ENV, json.dumps(spec))
    batch._preload_in_forkserver()
    assert batch.PRELOAD_ENV not in os.environ
    (key,) = batch._HEADS
    assert key[:2] == (str(data / "head.obj"), "m")
    monkeypatch.setenv(batch.PRELOAD_ENV, "{not json")
    batch._preload_in_forkserver()  # no exception: the workers would load what they need themselves
    assert batch.PRELOAD_ENV not in os.environ


def test_resume_skips_complete_output_sets_and_reruns_the_others(client, data, tmp_path):
    out = tmp_path / "out"
    first = batch.run_batch(inputs(data), out, head=data / "head.obj", params=PARAMS, client=client, quiet=True)
    assert first.counts["ok"] == 3
    stamps = {n: (out / n / "rest.npz").stat().st_mtime_ns for n in NAMES}
    (out / "g1" / "report.json").unlink()  # g1 incomplete: as if its writer died before the last file

    second = batch.run_batch(inputs(data), out, head=data / "head.obj", params=PARAMS, client=client, quiet=True)
    by_name = {r["name"]: r for r in second.rows}
    assert [by_name[n]["status"] for n in NAMES] == ["skipped", "ok", "skipped"]
    assert second.exit_code == 0
    assert (out / "g0" / "rest.npz").stat().st_mtime_ns == stamps["g0"]
    assert (out / "g2" / "rest.npz").stat().st_mtime_ns == stamps["g2"]
    assert (out / "g1" / "rest.npz").stat().st_mtime_ns != stamps["g1"]
    # a skipped groom's figures are read back from its output set
    for key in ("strands", "contacts", "residual", "unstable_strands", "q0_max", "q0_change_max"):
        assert by_name["g0"][key] == first.rows[0][key], key
    assert_nothing_half_written(out)
    assert read_csv(out)["g0"]["status"] == "skipped"

    third = batch.run_batch(inputs(data), out, head=data / "head.obj", params=PARAMS, client=client, quiet=True,
                            resume=False)
    assert [r["status"] for r in third.rows] == ["ok", "ok", "ok"]
    assert (out / "g0" / "rest.npz").stat().st_mtime_ns != stamps["g0"]


def test_solver_failure_is_reported_with_exit_code_2(client, data, tmp_path):
    out = tmp_path / "out"
    params = {**PARAMS, "solver": "gs", "max_sweeps": 1, "solver_tolerance": 1e-14}
    if "strict" in {f.name for f in dataclasses.fields(InversionParams)}:
        params["strict"] = True  # an unconverged but feasible solve is refused, not written
    summary = batch.run_batch(inputs(data, ["g0"]), out, head=data / "head.obj", params=params, client=client,
                              quiet=True)
    (row,) = summary.rows
    assert row["status"] == "solver_failure" and summary.exit_code == 2
    assert row["solve_status"] == "max_iter" and row["residual"] > 1e-14
    assert "did not converge" in row["error"] and str(data / "g0.obj") in row["error"]
    assert row["contacts"] > 0 and row["strands"] == 3
    assert not (out / "g0").exists()
    assert_nothing_half_written(out)
    if "strict" in params:  # without --strict the feasible forces are written, the warning goes to the summary
        del params["strict"]
        (row,) = batch.run_batch(inputs(data, ["g0"]), out, head=data / "head.obj", params=params, client=client,
                                 quiet=True).rows
        assert row["status"] == "ok" and row["solve_status"] == "feasible", row
        assert "FeasibleSolveWarning" in row["warnings"]


def test_scheduler_address(client, data, tmp_path):
    """--scheduler ADDRESS: the batch connects to a running scheduler (here the shared local one)."""
    out = tmp_path / "out"
    address = client.scheduler.address
    assert main(["batch", str(data / "g2.obj"), "--head", str(data / "head.obj"), "--contacts", "head",
                 "--contact-radius", "5e-4", "-o", str(out), "--scheduler", address, "-q"]) == 0
    summary = json.loads((out / "batch_summary.json").read_text())
    assert summary["workers"] == f"scheduler {address}"
    assert summary["grooms"][0]["worker"] in client.scheduler_info()["workers"]
    assert (out / "g2" / "report.json").is_file()


def test_a_writer_that_fails_leaves_no_partial_output(data, tmp_path, monkeypatch):
    """In process (the task function itself): the project's writer stages the set, so a failure while
    writing is reported in the row and leaves neither OUTDIR/<stem> nor a staging directory."""
    import groomtool.io.results as results

    def broken_write_json(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(results, "write_json", broken_write_json)
    out = tmp_path / "out"
    from groomtool.api import inversion_params

    row = batch.invert_one(data / "g0.obj", out, head=data / "head.obj", params=inversion_params(**PARAMS))
    assert row["status"] == "error" and "No space left" in row["error"]
    assert not (out / "g0").exists()
    assert list(out.iterdir()) == []


def test_the_progress_bar_is_the_packages_one_form_starting_at_the_skipped_grooms(capsys):
    from groomtool import timing

    bar = batch._progress_bar(10, 4, quiet=False)
    try:
        assert isinstance(bar, timing._bar_class())  # timing.progress: one form of bar (issue 18)
        assert bar.n == 4 and not bar.leave
        bar.update(3)  # the first task done: the time left is measured from here, not from the start-up
        assert bar.format_dict["bar_format"] == timing._UNMEASURED
    finally:
        bar.close()
    assert "batch:" in capsys.readouterr().err
    quiet = batch._progress_bar(10, 4, quiet=True)
    assert quiet.disable
    quiet.close()
    assert capsys.readouterr().err == ""


def test_exit_codes_and_bad_batches(data, tmp_path):
    rows = [{"status": s} for s in ("ok", "skipped")]
    assert batch.exit_code(rows) == 0
    assert batch.exit_code(rows + [{"status": "solver_failure"}]) == 2
    assert batch.exit_code(rows + [{"status": "solver_failure"}, {"status": "input_error"}]) == 1
    assert batch.exit_code(rows + [{"status": "worker_lost"}]) == 1
    other = tmp_path / "other"
    other.mkdir()
    (other / "g0.obj").write_text((data / "g0.obj").read_text())
    with pytest.raises(GroomError, match="g0.obj and .*g0.obj would both write g0/"):
        batch.run_batch([data / "g0.obj", other / "g0.obj"], tmp_path / "out", quiet=True)
    with pytest.raises(GroomError, match="no such head mesh"):
        batch.run_batch([data / "g0.obj"], tmp_path / "out", head=tmp_path / "nohead.obj", quiet=True)
    (tmp_path / "badhead.obj").write_text("v 0 0 0\nv nan 1 0\nv 1 0 0\nf 1 2 3\n")
    with pytest.raises(GroomError, match="badhead.obj"):  # once, before any worker starts
        batch.run_batch([data / "g0.obj"], tmp_path / "out", head=tmp_path / "badhead.obj", quiet=True)
    assert main(["batch", str(data / "g0.obj"), "--contacts", "head", "-o", str(tmp_path / "o"), "-q"]) == 1
    assert main(["batch", str(data / "g0.obj"), "--memory-limit", "lots", "-o", str(tmp_path / "o"), "-q"]) == 1


class KillMidWrite(distributed.WorkerPlugin):
    """In every worker: the first time ``name``'s report.json is written (its rest.npz and OBJ files are
    already staged), the worker process dies on the spot (os._exit), once per ``marker`` file."""

    def __init__(self, name: str, marker: str):
        self.name, self.marker = name, marker

    def setup(self, worker):
        import groomtool.io.results as results
        from groomtool.io.outset import PREFIX

        self.original = original = results.write_json
        tag, marker = f"{PREFIX}{self.name}-", self.marker

        def write_json(path, data):
            if tag in str(path):
                try:
                    fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                except FileExistsError:
                    return original(path, data)
                os.write(fd, f"{os.getpid()} {sorted(os.listdir(Path(path).parent))}".encode())
                os.close(fd)
                os._exit(1)
            return original(path, data)

        results.write_json = write_json

    def teardown(self, worker):
        import groomtool.io.results as results

        results.write_json = self.original


def test_alembic_is_a_batch_output_format(client, data, tmp_path):
    """--format abc is accepted like usd/vtp/hair: groom.abc in the set; without the optional alembic3d
    the batch says so once, before any groom is computed."""
    import importlib.util

    out = tmp_path / "out"
    if importlib.util.find_spec("alembic3d") is not None:
        summary = batch.run_batch(inputs(data, ["g0"]), out, head=data / "head.obj", params=PARAMS, client=client,
                                  quiet=True, formats=("npz", "json", "abc"))
        assert summary.rows[0]["status"] == "ok", summary.rows
        assert (out / "g0" / "groom.abc").is_file()
    else:
        with pytest.raises(GroomError, match="alembic3d"):
            batch.run_batch(inputs(data, ["g0"]), out, head=data / "head.obj", params=PARAMS, client=client,
                            quiet=True, formats=("npz", "json", "abc"))
        assert not (out / "g0").exists()
    with pytest.raises(GroomError, match="unknown output format"):
        batch.run_batch(inputs(data, ["g0"]), out, head=data / "head.obj", params=PARAMS, client=client,
                        quiet=True, formats=("npz", "fbx"))


def test_clothoid_batches_write_the_exporters_outputs(client, data, tmp_path):
    """--model clothoid with --format usd: the batch writes the clothoid's USD beside rest.npz (the
    exporters take both models), one complete set per groom."""
    out = tmp_path / "out"
    summary = batch.run_batch(inputs(data, ["g0"]), out, head=data / "head.obj", params={**PARAMS, "model": "clothoid"},
                              client=client, quiet=True, formats=("npz", "json", "usd"))
    assert summary.rows[0]["status"] == "ok", summary.rows
    assert sorted(p.name for p in (out / "g0").iterdir()) == ["groom.usdc", "report.json", "rest.npz"]
    from groomtool.io.results import read_result

    assert read_result(out / "g0").model == "clothoid"


def test_a_worker_killed_mid_write_is_retried_and_nothing_is_half_written(client, data, tmp_path):
    out = tmp_path / "out"
    marker = tmp_path / "killed"
    client.register_plugin(KillMidWrite("g1", str(marker)), name="kill-mid-write")
    try:
        summary = batch.run_batch(inputs(data), out, head=data / "head.obj", params=PARAMS, client=client,
                                  quiet=True)
    finally:
        client.unregister_worker_plugin("kill-mid-write")
    assert marker.exists(), "no worker was killed: the test proves nothing"
    killed_pid, staged = marker.read_text().split(" ", 1)
    assert "rest.npz" in staged and "report.json" not in staged  # killed with part of the set written
    assert [r["status"] for r in summary.rows] == ["ok", "ok", "ok"], summary.failed()
    assert summary.exit_code == 0
    g1 = summary.rows[1]
    assert g1["name"] == "g1" and (out / "g1" / "report.json").is_file()
    assert not g1["worker"].startswith("local:")
    assert_nothing_half_written(out)  # the killed worker's staging directory is gone too


@pytest.mark.parametrize("costs, workers", [([1.0] * 343, 2), ([5.0, 1.0, 1.0, 30.0, 2.0] * 40, 2),
                                            ([7.0, 3.0, 1.0], 2), ([1.0] * 10, 8), ([0.0] * 5, 2)])
def test_plan_tasks_covers_every_groom_once_largest_first_with_small_tasks_last(costs, workers):
    groups = batch.plan_tasks(costs, workers=workers)
    flat = [i for g in groups for i in g]
    assert sorted(flat) == list(range(len(costs)))  # every groom, exactly once
    ordered = [costs[i] for i in flat]
    assert ordered == sorted(costs, reverse=True)  # largest first
    assert len(groups[-1]) == 1  # the tail is single grooms: the workers finish together
    totals = [sum(costs[i] for i in g) for g in groups]
    assert all(a >= b - 1e-12 for a, b in zip(totals, totals[1:])) or max(totals) == min(totals)
    if len(costs) >= 100 and len(set(costs)) == 1:  # many equal small grooms: far fewer tasks than grooms
        assert len(groups) < len(costs) / 5


def test_estimated_costs_grow_with_strands_and_vertices_and_fall_back_to_the_file_size(tmp_path):
    """estimate_cost (plan_tasks' costs): monotone in strands x vertices read from synthetic headers, the same
    for the same groom in any format (file sizes differ 4x between .obj and .data), the size where no header."""
    import struct

    costs = []
    for strands, per in [(5, 100), (10, 100), (10, 200), (40, 100), (40, 400), (200, 100)]:
        p = tmp_path / f"s{strands}_{per}.data"
        with open(p, "wb") as f:  # only the count is real: the header is all estimate_cost reads
            f.write(struct.pack("<i", strands))
            f.write(b"\x00" * (4 * strands + 12 * strands * per))
        costs.append((strands * per * strands, batch.estimate_cost(p)))
    assert [c for _, c in sorted(costs)] == sorted(c for _, c in costs)  # monotone in strands x vertices
    assert all(c > batch.COST_FIXED_S for _, c in costs)
    groom, _ = example_groom(n_strands=6, seed=0)
    same = []
    for suffix in (".obj", ".data", ".hair"):
        save_groom(groom, tmp_path / f"g{suffix}")
        same.append(batch.estimate_cost(tmp_path / f"g{suffix}"))
    assert same[0] == same[1] == same[2]
    assert (tmp_path / "g.obj").stat().st_size > 3 * (tmp_path / "g.data").stat().st_size
    (tmp_path / "big.usd").write_bytes(b"\x00" * 240000)
    (tmp_path / "small.usd").write_bytes(b"\x00" * 24000)
    assert batch.estimate_cost(tmp_path / "big.usd") > batch.estimate_cost(tmp_path / "small.usd")
    assert batch.estimate_cost(tmp_path / "missing.data") == batch.COST_FIXED_S


def test_a_task_group_whose_worker_dies_is_rerun_groom_by_groom(client, data, tmp_path, monkeypatch):
    """Small grooms are grouped into tasks (plan_tasks); when a group's worker dies, its grooms are rerun
    one task each, so only a groom that kills its worker itself can be lost.  Here every group task
    kills its worker, and the plan is one group of all the grooms."""

    class KillGroups(distributed.WorkerPlugin):
        def __init__(self, marker):
            self.marker = marker

        def transition(self, key, start, finish, **kwargs):
            if finish == "executing" and "+" in str(key):
                with open(self.marker, "a") as f:
                    f.write(f"{key}\n")
                os._exit(1)

    many = tmp_path / "many"
    many.mkdir()
    names = [f"m{k}" for k in range(4)]
    for n in names:
        (many / f"{n}.obj").write_bytes((data / "g0.obj").read_bytes())
    monkeypatch.setattr(batch, "plan_tasks", lambda costs, workers: [list(range(len(costs)))])
    out = tmp_path / "out"
    marker = tmp_path / "killed"
    client.register_plugin(KillGroups(str(marker)), name="kill-groups")
    allowed_failures(client, 0)
    try:
        summary = batch.run_batch([many / f"{n}.obj" for n in names], out, head=data / "head.obj", params=PARAMS,
                                  client=client, quiet=True)
    finally:
        allowed_failures(client, 3)
        client.unregister_worker_plugin("kill-groups")
    assert marker.read_text().startswith("invert-m0+3-"), "the group task was not killed: the test proves nothing"
    assert [r["name"] for r in summary.rows] == names
    assert [r["status"] for r in summary.rows] == ["ok"] * len(names), summary.failed()
    assert summary.exit_code == 0
    assert_nothing_half_written(out)


def test_a_worker_that_always_dies_is_reported_after_the_retries(client, data, tmp_path):
    """allowed-failures is the retry budget: a groom whose worker dies every time is 'worker_lost'.
    (Last in this module: it restarts the shared cluster's workers.)"""

    class KillAlways(distributed.WorkerPlugin):
        def transition(self, key, start, finish, **kwargs):
            if finish == "executing" and "invert-g2-" in str(key):
                os._exit(1)

    out = tmp_path / "out"
    client.register_plugin(KillAlways(), name="kill-always")
    allowed_failures(client, 1)
    try:
        summary = batch.run_batch(inputs(data, ["g2"]), out, head=data / "head.obj", params=PARAMS, client=client,
                                  quiet=True)
    finally:
        allowed_failures(client, 3)
        client.unregister_worker_plugin("kill-always")
    (row,) = summary.rows
    assert row["status"] == "worker_lost" and "KilledWorker" in row["error"], row
    assert summary.exit_code == 1
    assert not (out / "g2").exists()
    assert_nothing_half_written(out)
