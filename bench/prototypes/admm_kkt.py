"""PROTOTYPE (issue 16; not part of the package, nothing imports it): ADMM on the inverse SOCQP with ONE sparse
LDL^T factorisation of the quasi-definite KKT matrix, reused at every iteration, stopped by the certified
rest-curvature bound (solvers/certificate.py).

    min 1/2 r^T W r + b^T r  s.t.  r = s,  s_i in K_mu_i,      W = H D H^T + 2 gamma I

    r-step:  (W + P) r = P (s - lam) - b,   P = diag(rho_i I_3),  rho_i = beta tr(W_ii) / 3
             as the quasi-definite system  [[D^-1, H^T], [H, -(2 gamma I + P)]] [v; r] = [0; -(P (s - lam) - b)]
             (v = -D H^T r; D^-1 > 0, -(2 gamma + rho) < 0: any symmetric permutation has an LDL^T, factored once
             by qdldl, Apache-2.0, clarabel's own dependency, with its AMD ordering)
    relaxed: r^ = alpha r + (1 - alpha) s
    s-step:  s = P_K(r^ + lam)           (per contact; s is always in the cones: an exact equilibrium)
    dual:    lam = lam + r^ - s
    optional Anderson mixing (memory --anderson) of the state (s, lam), restarted when the fixed-point
    residual grows tenfold over the best seen (as the Gauss-Seidel's).

Warm start: --warm Gauss-Seidel sweeps (s = their r, lam = -(W s + b) / rho, the ADMM fixed point's relation).
Every --every iterations the certified bound of inverse_problem.rest_curvature_error_bound (no line search) on s;
its CPU time is subtracted from the time axis (as in dense_solve_table.py).  Why this should work where
Gauss-Seidel stalls (docs/solvers.md section 12): the factorisation sees the whole coupled system, so the
directions that only 2 gamma holds (redundant contacts) and the collective ones of the strands' soft modes
are solved exactly in every r-step; ADMM only has to find the active set and the slip directions.

    OPENBLAS_NUM_THREADS=1 python bench/prototypes/admm_kkt.py /tmp/i16/ex1000.pkl [--beta 0.03] [--alpha 1.8]
        [--anderson 8] [--warm 20] [--target 1e-3] [--cpu 120]
(the pickle: bench/prototypes/dense_solve_table.py --save)
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import pickle  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

from groomtool.inverse_problem import rest_curvature_error_bound  # noqa: E402
from groomtool.solvers import solve_contact_problem  # noqa: E402
from groomtool.solvers.anderson import AndersonMixer  # noqa: E402
from groomtool.solvers.certificate import project_forces  # noqa: E402


def kkt_matrix(cp, rho):
    """Upper triangle (CSC) of [[D^-1, H^T], [H, -(2 gamma + rho)]] (diagonal D only)."""
    H = cp.H.tocsr()
    return sp.bmat([[sp.diags(1.0 / cp.D_data), H.T], [None, -sp.diags(2.0 * cp.gamma + rho)]], format="csc")


def admm(inv, cp, beta=0.03, alpha=1.8, anderson=8, warm=20, target=1e-3, cpu=120.0, every=10, log=print):
    import qdldl

    t0 = time.process_time()
    hook = 0.0
    H = cp.H.tocsr()
    n, m3 = H.shape[1], H.shape[0]
    b, mu = cp.b, cp.mu
    tr = np.repeat(np.einsum("kii->k", cp.diagonal_blocks()) / 3.0, 3)
    rho = beta * tr
    K = kkt_matrix(cp, rho)
    t_fac = time.process_time()
    solver = qdldl.Solver(K, upper=True)
    t_fac = time.process_time() - t_fac
    L_nnz = int(solver.factors()[0].nnz)
    log(f"KKT {n + m3:,} x {n + m3:,}, nnz(upper) {K.nnz:,}; LDL^T: L nnz {L_nnz:,}, {t_fac:.1f} s CPU")
    if warm:
        s = solve_contact_problem(cp, method="gs", max_iter=warm, tol=1e-14).r.copy()
    else:
        s = np.zeros(m3)
    lam = -cp.velocity(s) / rho
    rows = []
    rhs = np.zeros(n + m3)
    x = np.concatenate([s, lam])
    mixer = AndersonMixer(2 * m3, anderson, dtype=np.float64) if anderson else None
    restarts = 0
    xn = np.empty_like(x)
    k = 0
    while True:
        s_in, lam_in = x[:m3], x[m3:]
        rhs[n:] = b - rho * (s_in - lam_in)
        r = solver.solve(rhs)[n:]
        rh = alpha * r + (1.0 - alpha) * s_in
        s, _ = project_forces(rh + lam_in, mu)
        lam = lam_in + rh - s
        k += 1
        tx = np.concatenate([s, lam])
        if mixer is None:
            x = tx
        else:
            restarts += mixer.guarded_step(x, tx - x, xn)
            x, xn = xn, x
        if k % every == 0:
            th = time.process_time()
            u = cp.velocity(s)
            bound = rest_curvature_error_bound(inv, cp, s, u, line_search=False)["q0_error_bound"]
            res = cp.residual(s, u=u)
            hook += time.process_time() - th
            t = time.process_time() - t0 - hook
            rows.append((k, round(t, 2), res, bound))
            log(f"it {k} t {t:.1f} residual {res:.2e} q0 bound {bound:.2e}")
            if bound <= target or t > cpu:
                break
    return {"s": s, "history": rows, "factor_s": t_fac, "L_nnz": L_nnz, "restarts": restarts,
            "cpu_s": time.process_time() - t0 - hook}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("problem")
    ap.add_argument("--beta", type=float, default=0.03)
    ap.add_argument("--alpha", type=float, default=1.8)
    ap.add_argument("--anderson", type=int, default=8)
    ap.add_argument("--warm", type=int, default=20)
    ap.add_argument("--target", type=float, default=1e-3)
    ap.add_argument("--cpu", type=float, default=120.0)
    ap.add_argument("--every", type=int, default=10)
    ap.add_argument("--json")
    args = ap.parse_args()
    with open(args.problem, "rb") as f:
        data = pickle.load(f)
    out = admm(data["inv"], data["cp"], args.beta, args.alpha, args.anderson, args.warm, args.target, args.cpu,
               args.every)
    print(f"done: {out['cpu_s']:.1f} s CPU, final q0 bound {out['history'][-1][3]:.2e}")
    if args.json:
        with open(args.json, "a") as f:
            f.write(json.dumps({"config": f"admm beta {args.beta} alpha {args.alpha} anderson {args.anderson} "
                                          f"warm {args.warm}", "cpu_s": out["cpu_s"], "factor_s": out["factor_s"],
                                "L_nnz": out["L_nnz"], "history": out["history"]}) + "\n")


if __name__ == "__main__":
    main()
