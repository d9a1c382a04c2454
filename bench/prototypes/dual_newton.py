"""PROTOTYPE (not part of the package; issue 4 follow-up): semismooth Newton on the dof-space dual of the
inverse SOCQP, for contact-dense real grooms where block Gauss-Seidel stalls (docs/solvers.md section 9).

    min_q  1/2 q^T D^-1 q + 1/(4 gamma) sum_i ||P_K(-(H_i q + b_i))||^2,    r(q) = P_K(-(H q + b)) / (2 gamma)

Complementarity between r and u holds exactly for any q; only stationarity D^-1 q = H^T r(q) is iterated.
Each Newton system (D^-1 + H^T J H / (2 gamma)) dq = -grad is solved by CG preconditioned with a dense
Cholesky per strand (removes the redundant contact directions that stall Gauss-Seidel), Armijo on phi.

Measured (one core): a 150-strand patch of example_groom(1000) (8,921 contacts, 99 per strand) to a
residual of 6e-10 in 18 s (43 Newton steps, 2,009 CG iterations) where GS stalls at 1.8e-4 after 5000
sweeps and clarabel needs 40 s; the full example_groom(1000) (67.8k contacts) to 5.4e-7 in 190 s.  NOT
converged on a 2000-strand harolongo patch (43.7k contacts) within 240 s, nor from a cold start on the
bundled 200-strand example (6,094 contacts: residual ~10 after 60 Newton steps; a gamma continuation,
GAMMAS=..., or a warm start from GS, gsN, is needed).  Open: the slow cold start,
the Python per-strand loops (numba), scaling to a whole groom.

    python bench/prototypes/dump_problem.py harolongo.data --units cm --head head.obj --snap-roots -o P.npz
    python bench/prototypes/dual_newton.py P.npz GAMMA [pcg|direct] [max_newton] [time_limit] [R0.npy|gsN]

GAMMA is relative (the inversion's default 1e-4); env GAMMAS="1e-2,1e-3" runs a continuation first.
"""
import os
import sys
import time

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402
import scipy.sparse as sp  # noqa: E402

from groomtool.solvers import ContactProblem, solve_contact_problem  # noqa: E402


def load(path, gamma=None):
    """A problem saved by dump_problem.py (H in CSR parts, K^-1, w_scale, gamma, b, mu, dof offsets)."""
    z = np.load(path)
    H = sp.csr_matrix((z["Hd"], z["Hi"], z["Hp"]), shape=tuple(z["Hs"]))
    D = z["inv_k"] ** 2 / float(z["w_scale"])
    gam = float(z["gamma"]) if gamma is None else gamma
    return ContactProblem(H, D, z["offsets"], gam, z["b"], z["mu"]), z
import scipy.linalg as sla, scipy.sparse.linalg as spla
from numba import njit

@njit(cache=True)
def proj_jac(x, mu, p, J):
    """p_i = P_K(x_i), J_i = dP_K(x_i) for the cones {||t|| <= mu n}."""
    m = x.shape[0]
    for i in range(m):
        xn, t1, t2, mi = x[i, 0], x[i, 1], x[i, 2], mu[i]
        t = np.sqrt(t1 * t1 + t2 * t2)
        for a in range(3):
            for c in range(3):
                J[i, a, c] = 0.0
        if t <= mi * xn:
            p[i, 0], p[i, 1], p[i, 2] = xn, t1, t2
            J[i, 0, 0] = J[i, 1, 1] = J[i, 2, 2] = 1.0
        elif mi * t <= -xn:
            p[i, 0] = p[i, 1] = p[i, 2] = 0.0
        else:
            k = 1.0 / (1.0 + mi * mi)
            a_ = (xn + mi * t) * k
            e1, e2 = t1 / t, t2 / t
            p[i, 0], p[i, 1], p[i, 2] = a_, mi * a_ * e1, mi * a_ * e2
            e = (e1, e2)
            J[i, 0, 0] = k
            for a in range(2):
                J[i, 0, a + 1] = k * mi * e[a]
                J[i, a + 1, 0] = k * mi * e[a]
                for c in range(2):
                    J[i, a + 1, c + 1] = k * mi * mi * e[a] * e[c] + mi * a_ / t * ((1.0 if a == c else 0.0) - e[a] * e[c])

def main():
    import os
    stages = [float(x) for x in os.environ.get("GAMMAS", "").split(",") if x] + [float(sys.argv[2])]
    qw = None
    for k, gm in enumerate(stages):
        qw = solve(gm, qw, 1e-6 if k < len(stages) - 1 else 1e-9)

def solve(gamma, qw, stop):
    name = sys.argv[1]
    print("== gamma", gamma, flush=True)
    lin = sys.argv[3] if len(sys.argv) > 3 else "pcg"
    maxn = int(sys.argv[4]) if len(sys.argv) > 4 else 60
    tlim = float(sys.argv[5]) if len(sys.argv) > 5 else 170
    P, z = load(name, gamma)
    H = P.H.tocsr(); Hc = H.tocsc(); Ht = H.T.tocsr()
    m = P.n_contacts; n = P.n_dofs; g2 = 2 * gamma
    Dd = P.D_data.copy(); Dinv = 1 / Dd
    b = P.b.reshape(-1, 3); mu = P.mu
    off = P.dof_offsets
    p = np.empty((m, 3)); J = np.empty((m, 3, 3))
    def evaluate(q):
        x = -(H @ q).reshape(-1, 3) - b
        proj_jac(np.ascontiguousarray(x), mu, p, J)
        r = p.ravel() / g2
        phi = 0.5 * q @ (Dinv * q) + (p.ravel() @ p.ravel()) / (2 * g2)
        grad = Dinv * q - Ht @ r
        return phi, grad, r
    q = np.zeros(n)
    t0 = time.time(); tot_cg = 0
    if len(sys.argv) > 6:   # warm start: a GS iterate r0 -> q = D H^T r0, or 'gsN' = N GS sweeps first
        w = sys.argv[6]
        if w.startswith("gs"):
            g = solve_contact_problem(P, method="gs", form="assembled", max_iter=int(w[2:]))
            r0 = g.r; print("warm GS", g.iterations, f"res {g.residual:.2e} t {time.time()-t0:.1f}")
        else:
            r0 = np.load(w)
        q = Dd * (Ht.T @ r0) if False else Dd * (H.T @ r0)
    if qw is not None: q = qw.copy()
    phi, grad, r = evaluate(q)
    for it in range(maxn):
        res = P.residual(r)
        print(f"newton {it:3d} res {res:.2e} |grad| {np.linalg.norm(grad):.2e} obj {P.objective(r):.10e} cg {tot_cg} t {time.time()-t0:.1f}", flush=True)
        if res <= stop or time.time() - t0 > tlim:
            break
        # J as a sparse block diagonal
        rows = np.repeat(np.arange(3 * m).reshape(m, 3), 3, axis=1).ravel()
        cols = np.tile(np.arange(3 * m).reshape(m, 3), (1, 3)).ravel()
        Js = sp.csr_matrix((J.ravel(), (rows, cols)), shape=(3 * m, 3 * m))
        JH = (Js @ H).tocsc()
        def mv(v):
            return Dinv * v + (Ht @ (Js @ (H @ v))) / g2
        A = spla.LinearOperator((n, n), matvec=mv)
        if lin == "direct":
            M = (sp.diags(Dinv) + (Ht @ JH.tocsr()) / g2).tocsc()
            dq = spla.spsolve(M, -grad)
        else:
            facs = []
            for s in range(P.n_strands):
                a, c = off[s], off[s + 1]
                Hs = Hc[:, a:c]; JHs = JH[:, a:c]
                B = (Hs.T @ JHs).toarray() / g2 + np.diag(Dinv[a:c])
                facs.append(sla.cho_factor(B))
            def prec(v):
                out = np.empty_like(v)
                for s in range(P.n_strands):
                    a, c = off[s], off[s + 1]
                    out[a:c] = sla.cho_solve(facs[s], v[a:c])
                return out
            Mop = spla.LinearOperator((n, n), matvec=prec)
            gn = np.linalg.norm(grad)
            eta = min(0.1, np.sqrt(gn / np.linalg.norm(Dinv * q + 1e-300)))
            count = [0]
            def cb(xk): count[0] += 1
            dq, info = spla.cg(A, -grad, rtol=eta, M=Mop, maxiter=500, callback=cb)
            tot_cg += count[0]
        # Armijo on phi
        slope = grad @ dq; tstep = 1.0
        while True:
            phin, gradn, rn = evaluate(q + tstep * dq)
            if phin <= phi + 1e-4 * tstep * slope or tstep < 1e-8:
                break
            tstep *= 0.5
        q = q + tstep * dq; phi, grad, r = phin, gradn, rn
    np.save(f"{os.path.splitext(name)[0]}_g{gamma:g}_dualnewton.npy", r)
    return q


if __name__ == "__main__":
    main()
