"""MEASUREMENT ONLY (issue 16, item 4): the certified rest-curvature bound along a dual semismooth Newton
(the method of bench/prototypes/dual_newton.py, condensed) against Gauss-Seidel, on example_groom(N) with
its head and all contacts.  Each Newton iterate q gives l = D^-1/2 q and forces r(q) = P_K(-(H q + b)) / (2 gamma)
in their cones, certified by certificate.error_bound_with_dual.

    python bench/prototypes/dual_newton_bound.py --strands 300 [--warm 200] [--steps 30] [--time 300]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402
import scipy.sparse as sp  # noqa: E402
import scipy.sparse.linalg as spla  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dual_newton import proj_jac  # noqa: E402
from q0_bound import build  # noqa: E402

from groomtool.solvers import solve_contact_problem  # noqa: E402
from groomtool.solvers.certificate import error_bound_with_dual  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--strands", type=int, default=300)
    ap.add_argument("--contact-radius", type=float, default=3e-4)
    ap.add_argument("--warm", type=int, default=200, help="Gauss-Seidel sweeps before Newton")
    ap.add_argument("--steps", type=int, default=30)
    ap.add_argument("--time", type=float, default=300.0)
    ap.add_argument("--reference", default=None, help=".npy of a certified optimum r* (else none)")
    args = ap.parse_args()
    Pinv, P, q0_free = build(args.strands, args.contact_radius)
    scale = Pinv.f_scale * np.sqrt(Pinv.w_scale)
    H = P.H.tocsr()
    Hc, Ht = H.tocsc(), H.T.tocsr()
    m, n, g2 = P.n_contacts, P.n_dofs, 2 * P.gamma
    Dd = P.D_data.copy()
    Dinv, sqrt_d = 1 / Dd, np.sqrt(Dd)
    b, mu, off = P.b.reshape(-1, 3), P.mu, P.dof_offsets
    y_ref = None if args.reference is None else sqrt_d * (H.T @ np.load(args.reference))
    p, J = np.empty((m, 3)), np.empty((m, 3, 3))

    def evaluate(q):
        x = np.ascontiguousarray(-(H @ q).reshape(-1, 3) - b)
        proj_jac(x, mu, p, J)
        r = p.ravel() / g2
        return 0.5 * q @ (Dinv * q) + (p.ravel() @ p.ravel()) / (2 * g2), Dinv * q - Ht @ r, r

    def report(tag, r, lam, t):
        e = error_bound_with_dual(P, r, lam)
        y = sqrt_d * (H.T @ r)
        q0 = q0_free - scale * y
        rel = scale * e["bound"] / (np.linalg.norm(q0) - scale * e["bound"])
        true = "" if y_ref is None else f" true {scale * np.linalg.norm(y - y_ref) / np.linalg.norm(q0):.2e}"
        print(f"{tag:>12} residual {P.residual(r):.2e} q0 bound {rel:.2e}{true} t {t:.1f} s", flush=True)

    t0 = time.perf_counter()
    g = solve_contact_problem(P, method="gs", max_iter=args.warm, tol=1e-14)
    report(f"GS {args.warm}", g.r, sqrt_d * (H.T @ g.r), time.perf_counter() - t0)
    q = Dd * (H.T @ g.r)
    phi, grad, r = evaluate(q)
    for it in range(args.steps):
        report(f"newton {it}", r, q / sqrt_d, time.perf_counter() - t0)
        if time.perf_counter() - t0 > args.time:
            break
        rows = np.repeat(np.arange(3 * m).reshape(m, 3), 3, axis=1).ravel()
        cols = np.tile(np.arange(3 * m).reshape(m, 3), (1, 3)).ravel()
        Js = sp.csr_matrix((J.ravel(), (rows, cols)), shape=(3 * m, 3 * m))
        JH = (Js @ H).tocsc()
        facs = []
        for s in range(P.n_strands):
            a, c = off[s], off[s + 1]
            B = (Hc[:, a:c].T @ JH[:, a:c]).toarray() / g2 + np.diag(Dinv[a:c])
            facs.append(sla.cho_factor(B))

        def prec(v):
            out = np.empty_like(v)
            for s in range(P.n_strands):
                a, c = off[s], off[s + 1]
                out[a:c] = sla.cho_solve(facs[s], v[a:c])
            return out

        A = spla.LinearOperator((n, n), matvec=lambda v: Dinv * v + (Ht @ (Js @ (H @ v))) / g2)
        eta = min(0.1, np.sqrt(np.linalg.norm(grad) / np.linalg.norm(Dinv * q + 1e-300)))
        dq, _ = spla.cg(A, -grad, rtol=eta, M=spla.LinearOperator((n, n), matvec=prec), maxiter=500)
        slope, step = grad @ dq, 1.0
        while True:
            phin, gradn, rn = evaluate(q + step * dq)
            if phin <= phi + 1e-4 * step * slope or step < 1e-8:
                break
            step *= 0.5
        q, phi, grad, r = q + step * dq, phin, gradn, rn


if __name__ == "__main__":
    main()
