"""Gauss-Seidel options of issue 22 (symmetric sweeps, ...), each checked against clarabel's optimum and
against a direct restatement of what the option does."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from groomtool.solvers import solve_contact_problem, solve_socqp
from groomtool.solvers.gauss_seidel import AssembledOperator, MatrixFreeOperator

_spec = importlib.util.spec_from_file_location("bench_problems", Path(__file__).resolve().parents[1] / "bench" / "problems.py")
problems = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(problems)


def hair(m, **kw):
    return problems.make_hair_like(m, **kw)[0]


def test_backward_sweep_is_a_forward_sweep_in_reverse_order():
    """sweep_back after sweep == one forward sweep over the reversed contact order (assembled and
    matrix-free forms)."""
    P = hair(120, seed=3)
    W, b, mu = P.assemble_W(), P.b, P.mu
    m = P.n_contacts
    op = AssembledOperator.from_sparse(W, b, mu)
    r = np.zeros((m, 3))
    op.sweep(0, 1.0, r)
    after_forward = r.reshape(-1).copy()
    op.sweep_back(0, 1.0, r)
    rev = AssembledOperator.from_sparse(W, b, mu, np.arange(m)[::-1].copy())
    x = rev.to_internal(after_forward)
    rev.sweep(0, 1.0, x)
    expected = rev.to_external(x)
    assert np.abs(r.reshape(-1) - after_forward).max() > 1e-6  # the backward sweep did something
    np.testing.assert_allclose(r.reshape(-1), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    mf = MatrixFreeOperator(P)
    y = np.zeros((m, 3))
    mf.sweep(0, 1.0, y)
    mf.sweep_back(0, 1.0, y)
    np.testing.assert_allclose(y.reshape(-1), expected, rtol=0, atol=1e-10 * np.abs(expected).max())


@pytest.mark.parametrize("form", ["assembled", "matrix_free"])
def test_symmetric_gauss_seidel_reaches_clarabels_optimum(form):
    P = hair(250, seed=21)
    ref = solve_contact_problem(P, method="clarabel", polish=False)
    assert ref.status == "Solved"
    res = solve_contact_problem(P, tol=1e-10, form=form, symmetric=True)
    assert res.converged and res.residual <= 1e-10
    assert res.objective == pytest.approx(ref.objective, rel=1e-7)
    assert res.cone_violation <= 1e-12
    # forward sweeps, then symmetric ones once the residual is <= 1e-5 (checked every 5 sweeps: a
    # forward + backward pair steps over an odd check point, so the checks then come 6 sweeps apart)
    late = solve_contact_problem(P, tol=1e-10, form=form, symmetric=1e-5, check_every=5)
    assert late.converged and late.objective == pytest.approx(ref.objective, rel=1e-7)
    hist = late.info["history"]
    k = next(i for i, h in enumerate(hist) if h[1] <= 1e-5)
    assert {b[0] - a[0] for a, b in zip(hist[:k + 1], hist[1:k + 1])} == {5}
    assert {b[0] - a[0] for a, b in zip(hist[k:-1], hist[k + 1:-1])} == {6}
    plain = solve_contact_problem(P, tol=1e-10, form=form, symmetric=True, anderson=0, max_iter=20000)
    assert plain.converged and plain.objective == pytest.approx(ref.objective, rel=1e-7)
    assert plain.iterations % 2 == 0  # forward + backward pairs


def test_solve_socqp_does_not_use_blas_in_the_sweep_loop(monkeypatch):
    """No OpenBLAS call per sweep (its idle threads spin between calls, issue 22): np.linalg.norm and
    np.dot must not be reached from the Gauss-Seidel loop."""
    P = hair(200, seed=22)
    W = P.assemble_W()

    import groomtool.solvers.gauss_seidel as gs

    norm = np.linalg.norm

    def norm_rows_only(x, *a, **k):  # row norms (axis=...) are ufunc reductions, not BLAS
        if k.get("axis") is None:
            raise AssertionError("BLAS call inside the Gauss-Seidel loop")
        return norm(x, *a, **k)

    def forbidden(*a, **k):
        raise AssertionError("BLAS call inside the Gauss-Seidel loop")

    monkeypatch.setattr(gs.np.linalg, "norm", norm_rows_only)
    monkeypatch.setattr(gs.np, "dot", forbidden)
    res = gs.run_gauss_seidel(AssembledOperator.from_sparse(W, P.b, P.mu), tol=1e-9)
    assert res.converged and res.sweeps > 20


SHARED_GEN = Path(__file__).resolve().parents[2] / "shared" / "bench" / "gen_hair_problem.py"


@pytest.mark.skipif(not SHARED_GEN.exists(), reason="the shared generator (../shared/bench) is not checked out")
@pytest.mark.parametrize("pairing", ["random", "local"])
def test_shared_generator_problem_is_read_and_solved(tmp_path, pairing):
    """bench/problems.read_bogus_problem on a small file of the shared generator (the issue-22 headline
    problems): W symmetric with the stored lower blocks in place, and Gauss-Seidel with solve_socqp's
    defaults at clarabel's optimum."""
    import struct
    import subprocess
    import sys

    out = tmp_path / "p.bin"
    subprocess.run([sys.executable, str(SHARED_GEN), "--contacts", "150", "--pairing", pairing, "--gamma", "0.01",
                    "--seed", "3", "-o", str(out)], check=True, capture_output=True)
    W, b, mu = problems.read_bogus_problem(out)
    raw = out.read_bytes()
    n, nnzb = struct.unpack("<qq", raw[8:24])
    assert W.shape == (3 * n, 3 * n) and b.shape == (3 * n,) and mu.shape == (n,)
    rows = np.frombuffer(raw, "<i8", nnzb, 24)
    cols = np.frombuffer(raw, "<i8", nnzb, 24 + 8 * nnzb)
    vals = np.frombuffer(raw, "<f8", 9 * nnzb, 24 + 16 * nnzb).reshape(nnzb, 3, 3)
    k = int(np.flatnonzero(rows != cols)[0])
    i, j = rows[k], cols[k]
    np.testing.assert_array_equal(W[3 * i:3 * i + 3, 3 * j:3 * j + 3].toarray(), vals[k])
    np.testing.assert_array_equal(W[3 * j:3 * j + 3, 3 * i:3 * i + 3].toarray(), vals[k].T)
    assert abs(W - W.T).max() <= 1e-12 * abs(W).max()  # the file's diagonal blocks: symmetric to round-off
    ref = solve_socqp(W, b, mu, method="clarabel", polish=False)
    res = solve_socqp(W, b, mu)
    assert ref.status == "Solved"
    assert res.converged and res.residual <= 1e-8 and res.cone_violation <= 1e-12
    assert res.objective == pytest.approx(ref.objective, rel=1e-7)
    with pytest.raises(ValueError):
        bad = tmp_path / "bad.bin"
        bad.write_bytes(b"NOTAPROB" + raw[8:])
        problems.read_bogus_problem(bad)
