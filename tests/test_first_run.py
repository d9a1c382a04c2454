"""The first run: a cold numba cache is detected from numba's own index, said once, and compiled
before the bars start (groomtool.warmup)."""

import os
import subprocess
import sys
import textwrap

import pytest

from groomtool import warmup


def test_kernel_modules_are_found():
    names = warmup.kernel_modules()
    assert "groomtool.rods.superhelix" in names and "groomtool.fit.helix" in names
    assert set(warmup.FIRST_RUN_MODULES) <= set(names)


def test_cold_cache_is_detected_and_compiling_warms_it(tmp_path):
    """In a fresh process with an empty NUMBA_CACHE_DIR every kernel is cold; compiling two of them
    (sampling a tiny helix) makes exactly those warm."""
    code = textwrap.dedent("""
        import numpy as np
        from groomtool import warmup
        from groomtool.rods import superhelix as sh
        cold, total = warmup.cold_kernels(["groomtool.rods.superhelix"])
        print(cold, total)
        h = sh.SuperHelix(np.zeros((1, 3)), np.eye(3)[None], np.full((1, 2), 0.01),
                          np.full((1, 2, 3), 5.0), np.array([2]))
        sh.evaluate_positions(h, np.array([0]), np.array([0.005]))
        print(*warmup.cold_kernels(["groomtool.rods.superhelix"]))
    """)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    (cold0, total0), (cold1, total1) = [tuple(map(int, line.split())) for line in run.stdout.split("\n")[:2]]
    assert cold0 == total0 > 5
    assert total1 == total0 and 0 < cold1 < cold0  # what that call compiled (kinematics, positions), not all


def test_announce_only_when_cold(monkeypatch, capsys):
    calls = []
    monkeypatch.setattr(warmup, "warm_up", lambda params, with_head: calls.append(with_head) or 12.0)
    monkeypatch.setattr(warmup, "cold_kernels", lambda modules=None: (20, 20))
    assert warmup.announce_and_warm(None, with_head=True) is True
    err = capsys.readouterr().err
    assert err.count("compiling kernels (first run only") == 1 and "compiled in 12 s" in err
    assert calls == [True]
    monkeypatch.setattr(warmup, "cold_kernels", lambda modules=None: (3, 20))  # an edited module: lazily
    assert warmup.announce_and_warm(None) is False
    assert capsys.readouterr().err == "" and calls == [True]


def test_invert_warms_up_before_its_bars(tmp_path, monkeypatch, capsys):
    from groomtool.cli.main import EXIT_OK, main
    from groomtool.examples import write_example

    groom_path, head_path = write_example(tmp_path, n_strands=5, seed=1)
    seen = []
    monkeypatch.setattr(warmup, "cold_kernels", lambda modules=None: (20, 20))
    monkeypatch.setattr(warmup, "warm_up", lambda params, with_head: seen.append((params.contacts, with_head)) or 1.0)
    assert main(["invert", str(groom_path), "--head", str(head_path), "--contacts", "head",
                 "-o", str(tmp_path / "o")]) == EXIT_OK
    err = capsys.readouterr().err
    assert seen == [("head", True)]
    assert err.index("compiling kernels") < (err.index("fit") if "fit" in err else len(err))
    assert main(["invert", str(groom_path), "-q", "-o", str(tmp_path / "q")]) == EXIT_OK
    assert seen == [("head", True)]  # --quiet: no bars, no warm-up


@pytest.mark.skipif(os.environ.get("GROOMTOOL_SLOW") is None, reason="compiles every kernel (minutes): GROOMTOOL_SLOW=1")
def test_real_warm_up_compiles_the_first_run_modules(tmp_path):
    code = "from groomtool import warmup; warmup.warm_up(); print(*warmup.cold_kernels(warmup.FIRST_RUN_MODULES))"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=1800)
    assert run.returncode == 0, run.stderr[-2000:]
    cold, total = map(int, run.stdout.split())
    assert total > 0 and cold < warmup.COLD_FRACTION * total
