"""An output directory is one atomic set: interrupted at any moment (SIGINT, SIGKILL, a failure
between the renames) it holds the old complete set or the new complete set, never a mix; no stale
files of an earlier run; the input is never overwritten; a bad output path fails before computing."""

import json
import os
import signal
import time

import numpy as np
import pytest

from groomtool.cli.main import EXIT_OK, EXIT_USER_ERROR, main
from groomtool.examples import write_example
from groomtool.invert import invert_groom
from groomtool.io import load_groom, outset
from groomtool.io.results import write_result

SET = {"rest.npz", "rest_shape.obj", "fitted.obj", "report.json"}


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    d = tmp_path_factory.mktemp("example")
    return write_example(d, n_strands=6, seed=5)


@pytest.fixture(scope="module")
def result(example):
    return invert_groom(load_groom(example[0]))


def stamped(result, run: int):
    result.report["run"] = run
    result.extra_arrays = {"run": np.array(run)}
    return result


def run_of(out) -> int:
    """The run id of a complete set; fails on a mixed or partial one."""
    assert {p.name for p in out.iterdir()} == SET, sorted(p.name for p in out.iterdir())
    with np.load(out / "rest.npz") as z:
        npz_run = int(z["run"])
    assert json.loads((out / "report.json").read_text())["run"] == npz_run
    assert load_groom(out / "fitted.obj").n_strands == 6
    return npz_run


def leftovers(out):
    return [p.name for p in out.parent.iterdir() if p.name.startswith(outset.PREFIX)]


def test_failure_while_writing_keeps_the_old_set(result, tmp_path, monkeypatch):
    out = tmp_path / "out"
    write_result(stamped(result, 1), out)
    from groomtool.io import results

    def fail(path, data):
        raise KeyboardInterrupt

    monkeypatch.setattr(results, "write_json", fail)  # rest.npz and the OBJs are written by then
    with pytest.raises(KeyboardInterrupt):
        write_result(stamped(result, 2), out)
    assert run_of(out) == 1 and not leftovers(out)


@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_failure_between_renames_keeps_one_set(result, tmp_path, monkeypatch, exchange):
    out = tmp_path / "out"
    write_result(stamped(result, 1), out)
    calls = []
    if exchange:
        real_exchange = outset.exchange

        def swap(a, b):  # interrupted right after the atomic exchange
            calls.append((a, b))
            assert real_exchange(a, b)
            raise KeyboardInterrupt

        monkeypatch.setattr(outset, "exchange", swap)
    else:
        monkeypatch.setattr(outset, "exchange", lambda a, b: False)
        real_rename = os.rename

        def rename(a, b):  # interrupted between "old aside" and "new in"
            calls.append((a, b))
            real_rename(a, b)
            raise KeyboardInterrupt

        monkeypatch.setattr(outset.os, "rename", rename)
    with pytest.raises(KeyboardInterrupt):
        write_result(stamped(result, 2), out)
    monkeypatch.undo()
    assert calls  # the swap was reached
    outset.recover(out)
    assert run_of(out) == (2 if exchange else 1) and not leftovers(out)


def test_format_npz_leaves_no_stale_files(result, tmp_path):
    out = tmp_path / "out"
    write_result(stamped(result, 1), out)
    (out / "check.json").write_text("{}")
    (out / "notes.txt").write_text("mine")  # not an output: carried over
    write_result(stamped(result, 2), out, formats=("npz",))
    assert {p.name for p in out.iterdir()} == {"rest.npz", "notes.txt"}
    assert (out / "notes.txt").read_text() == "mine"


def test_foreign_subdirectory_is_refused_before_computing(result, example, tmp_path, capsys):
    out = tmp_path / "out"
    write_result(stamped(result, 1), out)
    (out / "sim").mkdir()
    (out / "sim" / "frame_0000.obj").write_text("v 0 0 0\n")
    from groomtool.groom import GroomError

    with pytest.raises(GroomError, match="holds the directory 'sim'"):
        write_result(stamped(result, 2), out)
    assert main(["invert", str(example[0]), "-o", str(out), "-q"]) == EXIT_USER_ERROR
    assert "holds the directory 'sim'" in capsys.readouterr().err
    assert run_of_with(out, {"sim"}) == 1 and (out / "sim" / "frame_0000.obj").exists()


def test_current_directory_is_refused(result, tmp_path, monkeypatch):
    from groomtool.groom import GroomError

    (tmp_path / "notes.txt").write_text("mine")
    monkeypatch.chdir(tmp_path)
    for outdir in (".", str(tmp_path)):
        with pytest.raises(GroomError, match="current directory"):
            outset.check_target(outdir)
        with pytest.raises(GroomError, match="current directory"):
            write_result(stamped(result, 1), outdir)
    assert {p.name for p in tmp_path.iterdir()} == {"notes.txt"}


def run_of_with(out, extra) -> int:
    with np.load(out / "rest.npz") as z:
        run = int(z["run"])
    assert {p.name for p in out.iterdir()} == SET | set(extra)
    return run


def _child_writes(result, out):
    """In a forked child: write sets 2, 3, 4, ... until killed.  SIGINT raises KeyboardInterrupt even
    where the test runner was started with SIGINT ignored (a background job of a non-interactive
    shell inherits SIG_IGN, and the child would then write on until its 10,000 runs are done)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        for run in range(2, 10_000):
            write_result(stamped(result, run), out)
    except KeyboardInterrupt:
        os._exit(130)
    finally:
        os._exit(0)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
@pytest.mark.parametrize("exchange", [True, False], ids=["renameat2", "two-renames"])
def test_killed_at_any_moment_leaves_one_complete_set(result, tmp_path, sig, exchange, monkeypatch):
    if not exchange:
        monkeypatch.setattr(outset, "_RENAMEAT2", None)
    rng = np.random.default_rng(int(sig) + 10 * exchange)
    seen = set()
    for trial in range(6):
        out = tmp_path / f"out{trial}"
        write_result(stamped(result, 1), out)
        pid = os.fork()
        if pid == 0:
            _child_writes(result, out)
        time.sleep(float(rng.uniform(0.0, 0.4)))
        os.kill(pid, sig)
        os.waitpid(pid, 0)
        outset.recover(out)  # what the next run or reader does
        seen.add(run_of(out))
        assert not leftovers(out)
    assert len(seen) >= 1


def test_cli_interrupted_run_leaves_old_set(example, tmp_path):
    """A real ``groom invert`` interrupted by SIGINT or SIGKILL at several moments."""
    groom_path, _ = example
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "-o", str(out), "-q"]) == EXIT_OK
    before = {name: (out / name).read_bytes() for name in SET}
    for delay, sig in ((0.0, signal.SIGINT), (0.05, signal.SIGKILL), (0.2, signal.SIGINT), (0.5, signal.SIGKILL)):
        pid = os.fork()
        if pid == 0:
            code = 3
            try:
                code = main(["invert", str(groom_path), "-o", str(out), "-q", "--tolerance", "1e-4"])
            finally:
                os._exit(code)
        time.sleep(delay)
        os.kill(pid, sig)
        os.waitpid(pid, 0)
        outset.recover(out)
        names = {p.name for p in out.iterdir()}
        assert names == SET
        report = json.loads((out / "report.json").read_text())
        new = report["fit"]["tolerance_m"] == pytest.approx(1e-4)
        old_npz = (out / "rest.npz").read_bytes() == before["rest.npz"]
        assert old_npz != new  # the npz belongs to the same run as the report
        assert not leftovers(out)


# ------------------------------------------------------------------ input and output path checks
def test_input_inside_the_output_set_is_refused(example, tmp_path, capsys):
    groom_path, _ = example
    out = tmp_path / "out"
    assert main(["invert", str(groom_path), "-o", str(out), "-q"]) == EXIT_OK
    fitted = (out / "fitted.obj").read_bytes()
    assert main(["invert", str(out / "fitted.obj"), "-o", str(out), "-q"]) == EXIT_USER_ERROR
    err = capsys.readouterr().err
    assert "fitted.obj" in err and "output directory" in err and "Traceback" not in err
    assert (out / "fitted.obj").read_bytes() == fitted
    # another directory is fine
    assert main(["invert", str(out / "fitted.obj"), "-o", str(tmp_path / "other"), "-q"]) == EXIT_OK


def test_output_path_checked_before_computing(example, tmp_path, capsys, monkeypatch):
    groom_path, _ = example
    import sys

    inv = sys.modules["groomtool.invert"]

    def must_not_run(*a, **k):
        raise AssertionError("computed before checking the output path")

    monkeypatch.setattr(inv, "invert_groom", must_not_run)
    afile = tmp_path / "afile"
    afile.write_text("x")
    for bad in (afile, afile / "sub"):
        assert main(["invert", str(groom_path), "-o", str(bad), "-q"]) == EXIT_USER_ERROR
        err = capsys.readouterr().err
        assert str(afile) in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_output_dir(example, tmp_path, capsys):
    groom_path, _ = example
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        assert main(["invert", str(groom_path), "-o", str(ro / "out"), "-q"]) == EXIT_USER_ERROR
        assert "not writable" in capsys.readouterr().err
    finally:
        ro.chmod(0o700)


def test_disk_full_leaves_the_old_set(result, tmp_path, monkeypatch):
    from groomtool.groom import GroomError
    from groomtool.io import results

    out = tmp_path / "out"
    write_result(stamped(result, 1), out)

    def full(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(results, "write_json", full)
    with pytest.raises(GroomError, match="No space left on device.*unchanged"):
        write_result(stamped(result, 2), out)
    assert run_of(out) == 1 and not leftovers(out)
