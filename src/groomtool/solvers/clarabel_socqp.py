"""The exact SOCQP by clarabel's interior-point method, kept sparse through the factor of W.

    min_r 1/2 r^T W r + b^T r   s.t.  r_i in K_mu_i,      W = H D H^T + 2 gamma I

With D = L L^T per strand (L = sqrt(D) when D is diagonal, its Cholesky factor otherwise) and the extra
variables y = L^T H^T r (n of them), the problem clarabel sees is

    min_{r, y} 1/2 ||y||^2 + gamma ||r||^2 + b^T r
    s.t.  y - L^T H^T r = 0                                  (zero cone, n rows)
          (mu r_N, r_T) in SOC(3)   if mu <= 1               (clarabel: s_0 >= ||s_1:||)
          (r_N, r_T / mu) in SOC(3) if mu > 1                (the same cone, coefficients <= 1)
          r_T = 0 (zero cone) and r_N >= 0 (nonnegative)     if mu = 0  (SOC(3) would leave r_N free)

so P = diag(2 gamma I, I) and the KKT matrix keeps the sparsity of H instead of W's fill.
clarabel writes constraints as A x + s = b, s in cone, hence the minus signs below.
The assembled form (``solve_assembled``) passes P = W directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

import clarabel


@dataclass
class ClarabelOutcome:
    r: np.ndarray
    status: str
    iterations: int
    objective: float
    solve_s: float  # clarabel's own solve time
    setup_s: float  # building the matrices and clarabel's setup
    kkt_size: int


def _cone_rows(mu: np.ndarray):
    """Rows (A, as COO triplets over the 3m r-variables) and cones for the friction constraints."""
    m = mu.shape[0]
    zero = np.flatnonzero(mu == 0.0)
    soc = np.flatnonzero(mu > 0.0)
    rows, cols, vals = [], [], []
    row = 0
    # zero cone: r_T = 0 for frictionless contacts (s = -A x = 0)
    for a in (1, 2):
        rows.append(row + np.arange(zero.size))
        cols.append(3 * zero + a)
        vals.append(-np.ones(zero.size))
        row += zero.size
    n_zero = 2 * zero.size
    # nonnegative: r_N >= 0 for frictionless contacts
    rows.append(row + np.arange(zero.size))
    cols.append(3 * zero)
    vals.append(-np.ones(zero.size))
    row += zero.size
    n_nonneg = zero.size
    # second-order cones, 3 rows each: s = (c_N r_N, c_T r_T)
    mus = mu[soc]
    cN = np.where(mus <= 1.0, mus, 1.0)
    cT = np.where(mus <= 1.0, 1.0, 1.0 / np.where(mus > 0, mus, 1.0))
    base = row + 3 * np.arange(soc.size)
    for a, coef in ((0, cN), (1, cT), (2, cT)):
        rows.append(base + a)
        cols.append(3 * soc + a)
        vals.append(-coef)
    row += 3 * soc.size
    assert row == 2 * zero.size + zero.size + 3 * soc.size and m == zero.size + soc.size
    return (np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)), row, n_zero, n_nonneg, soc.size


@dataclass(frozen=True)
class Settings:
    """What solve_factored and solve_assembled take (keywords): stopping tolerance (clarabel's gap,
    feasibility and KKT-ratio tolerances), iteration budget, threads, the KKT linear solver ("auto":
    clarabel's default; "qdldl", "faer"), clarabel's own printing, a time limit in seconds."""

    tol: float = 1e-9
    max_iter: int = 200
    threads: int = 1
    linear_solver: str = "auto"
    verbose: bool = False
    time_limit: float | None = None

    def clarabel(self):
        s = clarabel.DefaultSettings()
        s.verbose = self.verbose
        s.max_iter = int(self.max_iter)
        s.tol_gap_abs = self.tol
        s.tol_gap_rel = self.tol
        s.tol_feas = self.tol
        s.tol_ktratio = max(self.tol, 1e-10)
        s.max_threads = int(self.threads)
        if self.time_limit is not None:
            s.time_limit = float(self.time_limit)
        if self.linear_solver != "auto":
            s.direct_solve_method = self.linear_solver
        return s


def _run(P, q, A, bvec, cones, settings: Settings, t0: float, m3: int, objective) -> ClarabelOutcome:
    """clarabel.DefaultSolver(...).solve(), falling back to qdldl if the requested linear solver is absent;
    r = the first m3 entries of clarabel's x (all of them in the assembled form)."""
    opts = settings.clarabel()
    setup_s = time.perf_counter() - t0
    try:
        solver = clarabel.DefaultSolver(P, q, A, bvec, cones, opts)
    except Exception:
        if settings.linear_solver in ("auto", "qdldl"):
            raise
        opts.direct_solve_method = "qdldl"
        solver = clarabel.DefaultSolver(P, q, A, bvec, cones, opts)
    sol = solver.solve()
    r = np.array(sol.x[:m3])
    return ClarabelOutcome(
        r=r,
        status=str(sol.status),
        iterations=int(sol.iterations),
        objective=objective(r),
        solve_s=float(sol.solve_time),
        setup_s=setup_s,
        kkt_size=int(P.shape[0] + A.shape[0]),
    )


def _cones(n_eq: int, n_zero: int, n_nonneg: int, n_soc: int):
    cones = []
    if n_eq + n_zero:
        cones.append(clarabel.ZeroConeT(n_eq + n_zero))
    if n_nonneg:
        cones.append(clarabel.NonnegativeConeT(n_nonneg))
    soc = clarabel.SecondOrderConeT(3)
    cones.extend([soc] * n_soc)
    return cones


def strand_factor(problem) -> sp.csr_matrix:
    """L with D = L L^T, block-diagonal per strand (sqrt of a diagonal block, Cholesky of a dense one)."""
    mats = []
    for d in problem.D_blocks:
        if d.ndim == 1:
            if np.any(d < 0):
                raise ValueError("a diagonal D block has a negative entry")
            mats.append(sp.diags(np.sqrt(d)))
        else:
            mats.append(sp.csr_matrix(sla.cholesky(0.5 * (d + d.T), lower=True)))
    return sp.block_diag(mats, format="csr")


def solve_factored(problem, **settings) -> ClarabelOutcome:
    """Solve the SOCQP of a ContactProblem with clarabel in the sparse factored form (module docstring).
    ``settings``: the fields of :class:`Settings` (tol=1e-9, max_iter=200, threads=1, linear_solver="auto",
    verbose=False, time_limit=None)."""
    t0 = time.perf_counter()
    settings = Settings(**settings)
    m3, n = problem.H.shape
    mu = problem.mu
    LtHt = (problem.H @ strand_factor(problem)).T.tocsr()  # (n, 3m) = L^T H^T
    P = sp.block_diag([2.0 * problem.gamma * sp.identity(m3), sp.identity(n)], format="csc")
    P = sp.triu(P, format="csc")
    q = np.concatenate([problem.b, np.zeros(n)])
    (cr, cc, cv), n_cone_rows, n_zero, n_nonneg, n_soc = _cone_rows(mu)
    # rows 0..n-1: -L^T H^T r + y = 0 ; then the cone rows (zero cone for r_T first, so they join the
    # equality block)
    eq = sp.hstack([-LtHt, sp.identity(n)], format="csr")
    cone = sp.csr_matrix((cv, (cr, cc)), shape=(n_cone_rows, m3 + n))
    A = sp.vstack([eq, cone], format="csc")
    bvec = np.zeros(n + n_cone_rows)
    return _run(P, q, A, bvec, _cones(n, n_zero, n_nonneg, n_soc), settings, t0, m3, problem.objective)


def solve_assembled(W, b: np.ndarray, mu: np.ndarray, **settings) -> ClarabelOutcome:
    """Solve min 1/2 r^T W r + b^T r, r_i in K_mu_i with clarabel and P = W (W sparse, symmetric PSD).
    ``settings``: as solve_factored."""
    t0 = time.perf_counter()
    settings = Settings(**settings)
    W = sp.csr_matrix(W, dtype=np.float64)
    m3 = W.shape[0]
    b = np.asarray(b, dtype=np.float64).reshape(-1)
    mu = np.broadcast_to(np.asarray(mu, dtype=np.float64), (m3 // 3,))
    P = sp.triu(0.5 * (W + W.T), format="csc")
    (cr, cc, cv), n_rows, n_zero, n_nonneg, n_soc = _cone_rows(mu)
    A = sp.csc_matrix((cv, (cr, cc)), shape=(n_rows, m3))
    return _run(P, b, A, np.zeros(n_rows), _cones(0, n_zero, n_nonneg, n_soc), settings, t0, m3,
                lambda r: float(0.5 * r @ (W @ r) + b @ r))
