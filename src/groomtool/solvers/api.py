"""Public entry points: solve_socqp, solve_coulomb (assembled W) and solve_contact_problem (factored).

All three go through one dispatch, :func:`_solve`, on a target that says how the problem at hand builds
each method's operator (_AssembledTarget, _FactoredTarget): a new method is one branch there.
Every solver returns a SolveResult whose ``residual`` is the measure of residual.py, computed on the
returned r whatever the method, so results of different methods compare directly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from . import residual as _res
from .admm import run_admm
from .apgd import FactoredMatvec, UpperMatvec, run_apgd
from .blocks import UpperBlockDelassus, contact_segments
from .clarabel_socqp import solve_assembled, solve_factored
from .coulomb_fixed_point import run_coulomb_fixed_point
from .cones import law_code
from .gauss_seidel import AssembledOperator, MatrixFreeOperator, contact_order, run_gauss_seidel
from .problem import ContactProblem

DEFAULT_MAX_ITER = {"gs": 5000, "fixed_point": 5000, "apgd": 20000, "clarabel": 200, "admm": 5000}
SOC_METHODS = ("gs", "apgd", "clarabel", "admm")
COULOMB_METHODS = ("gs", "fixed_point")
COULOMB_STALL_WINDOW = 200  # sweeps without halving the residual before "auto" switches to fixed_point
ASSEMBLED_MEMORY_CAP = 4 << 30  # bytes of 3x3 blocks above which "auto" goes matrix-free


@dataclass
class SolveResult:
    """Outcome of a contact solve.

    r:              (3m,) reactions, [N, T1, T2] per contact.
    status:         "solved", "max_iter", "time_limit", "stalled" (gs with give_up: info["projected_sweeps"]),
                    "certified" (gs: the caller's ``stop`` rule accepted r before the residual reached tol;
                    converged stays False), "diverged" (iterative methods) or clarabel's status.
    converged:      residual <= tol.  clarabel: it reported Solved and its point, polished by Gauss-Seidel
                    sweeps where its residual was above tol (info: polish_sweeps, clarabel_residual), meets tol.
    residual:       max_i ||r_i - P_K(r_i - rho_i u_eff_i)|| / max_i rho_i ||b_i||   (residual.py).
    iterations:     sweeps (gs), iterations (apgd, clarabel).
    objective:      1/2 r^T W r + b^T r (the SOCQP's objective; informative only for the Coulomb law).
    cone_violation: max_i max(0, ||r_T,i|| - mu_i r_N,i).
    time_s:         wall time including set-up (assembly, factorisation, ...).
    method:         "gs", "apgd", "clarabel", "fixed_point" or "auto" (Coulomb; see info["switched_to"]).
    info:           details: form, setup_s, solve_s, local_failures, history [(iteration, residual, s)], ...
    """

    r: np.ndarray
    status: str
    converged: bool
    residual: float
    iterations: int
    objective: float
    cone_violation: float
    time_s: float
    method: str
    info: dict = field(default_factory=dict)


def _iterative_status(converged: bool, residual: float, iterations: int, max_iter: int, info: dict) -> str:
    if converged:
        return "solved"
    if info.get("stopped_by") == "stop":
        return "certified"
    if not np.isfinite(residual):
        return "diverged"
    if info.get("projected_sweeps") is not None:
        return "stalled"
    return "max_iter" if iterations >= max_iter else "time_limit"


def _resolve_method(law: str, method: str) -> str:
    """'auto' -> 'gs' (SOC) / 'auto' kept for Coulomb (direct GS, then the fixed point if it stalls)."""
    allowed = SOC_METHODS if law == "soc" else COULOMB_METHODS
    if method == "auto":
        return "gs" if law == "soc" else "auto"
    if method not in allowed:
        raise ValueError(
            f"method {method!r} does not solve the {law} law: use one of {allowed + ('auto',)}"
            + (" (the Coulomb law is not an optimisation problem)" if law == "coulomb" else "")
        )
    return method


def _run_gs_family(op, law, method, tol, max_sweeps, r0, options, info):
    """Gauss-Seidel (SOC or Coulomb), the Coulomb fixed point, or 'auto' (GS, then fixed point if it
    stalls).  Returns (r, iterations, converged, residual of the solver)."""
    if method == "fixed_point":
        fp_opts = {k: v for k, v in options.items() if k in ("anderson", "time_limit", "check_every", "max_outer", "scale")}
        out = run_coulomb_fixed_point(op, tol=tol, max_sweeps=max_sweeps, r0=r0, **fp_opts)
        info.update(local_failures=out.local_failures, history=out.history, outer_iterations=out.outer,
                    solve_s=out.solve_s)
        return out.r, out.sweeps, out.converged, out.residual
    stall = COULOMB_STALL_WINDOW if method == "auto" else None
    out = run_gauss_seidel(op, law, tol=tol, max_sweeps=max_sweeps, r0=r0, stall_window=stall, **options)
    info.update(local_failures=out.local_failures, history=out.history, solve_s=out.solve_s)
    if out.newton is not None:
        info["newton"] = out.newton
    if out.cluster is not None:
        info["cluster"] = out.cluster
    if method == "auto" and not out.converged and out.sweeps < max_sweeps and np.isfinite(out.residual):
        fp_opts = {k: v for k, v in options.items() if k in ("anderson", "time_limit", "check_every", "scale")}
        fp = run_coulomb_fixed_point(op, tol=tol, max_sweeps=max_sweeps - out.sweeps, r0=out.r, **fp_opts)
        info.update(switched_to="fixed_point", gs_sweeps=out.sweeps, outer_iterations=fp.outer,
                    local_failures=out.local_failures + fp.local_failures,
                    history=out.history + [(out.sweeps + h[0], h[1], out.solve_s + h[2]) for h in fp.history[1:]],
                    solve_s=out.solve_s + fp.solve_s)
        return fp.r, out.sweeps + fp.sweeps, fp.converged, fp.residual
    if out.projected_sweeps is not None:  # stopped by give_up
        info["projected_sweeps"] = out.projected_sweeps
    if out.stopped_by_rule:  # the caller's stop rule accepted r (status "certified")
        info["stopped_by"] = "stop"
    return out.r, out.sweeps, out.converged, out.residual


POLISH_MAX_SWEEPS = 2000


def _polish_with_gs(op, r, residual, tol, info, status, callback=None, scale=None):
    """clarabel's interior point stops on its own duality gap, which leaves the natural-map residual
    (residual.py) at 1e-7..1e-4 on hair problems.  A few Gauss-Seidel sweeps from its point (each
    contact's local problem solved exactly, warm-started at the optimum) bring it below tol; the
    result then converged only if Gauss-Seidel did.  Returns (r, converged, status)."""
    if residual <= tol or not np.all(np.isfinite(r)):
        return r, residual <= tol, status
    out = run_gauss_seidel(op, "soc", tol=tol, max_sweeps=POLISH_MAX_SWEEPS, r0=r, callback=callback, scale=scale)
    info.update(polish_sweeps=out.sweeps, polish_s=out.solve_s, clarabel_status=status,
                clarabel_residual=float(residual))
    if not out.converged:
        return out.r, False, f"{status}, polish stopped at {out.residual:.1e}"
    return out.r, True, "Solved"


def _resolve_order(order, H):
    if order is None or isinstance(order, str):
        return contact_order(H, order or "natural")
    return np.ascontiguousarray(order, dtype=np.int64)


# ----------------------------------------------------------------------------------------------
# assembled W
# ----------------------------------------------------------------------------------------------
def _check_assembled(W, b, mu):
    W = sp.csr_matrix(W, dtype=np.float64)
    n = W.shape[0]
    if W.shape[0] != W.shape[1] or n % 3:
        raise ValueError(f"W must be square with 3m rows (3x3 blocks, normal first), got {W.shape}")
    b = np.ascontiguousarray(b, dtype=np.float64).reshape(-1)
    if b.shape[0] != n:
        raise ValueError(f"b has {b.shape[0]} entries, W has {n} rows")
    mu = np.ascontiguousarray(np.broadcast_to(np.asarray(mu, dtype=np.float64), (n // 3,)))
    if np.any(mu < 0) or not np.all(np.isfinite(mu)):
        raise ValueError("friction coefficients must be finite and >= 0")
    return W, b, mu


class _AssembledTarget:
    """What the one dispatch (:func:`_solve`) needs from a problem given as an assembled W."""

    form = "assembled"  # of the Gauss-Seidel and APGD operators
    clarabel_form = "assembled"
    # clarabel's point goes through _polish_with_gs even within tol, so it counts as converged by its
    # residual whatever clarabel's status (AlmostSolved within tol: converged; non-finite: not); the
    # factored target keeps clarabel's verdict then.  The two entry points have always differed here.
    polish_within_tol = True

    def __init__(self, W, b, mu):
        self.W, self.b, self.mu = W, b, mu
        self.gs_op = None  # the Gauss-Seidel operator of the solve, whose rho the residual reuses
        self._scale_rho = None

    def gs_operator(self, order):
        order = _resolve_order(order, self.W)
        self.gs_op = AssembledOperator.from_sparse(self.W, self.b, self.mu, order)
        return self.gs_op

    def apgd_operator(self):
        """(x -> W x, rho, b)."""
        U = UpperBlockDelassus.from_sparse(self.W)
        return UpperMatvec(U), _res.rho_from_diagonal(U.diagonal()), self.b

    def clarabel(self, max_iter, options):
        return solve_assembled(self.W, self.b, self.mu, max_iter=max_iter, **options)

    def polish_operator(self):
        return AssembledOperator.from_sparse(self.W, self.b, self.mu)

    def velocity(self, r):
        return self.W @ r + self.b

    def residual(self, r, u, law, scale):
        if self._scale_rho is None:
            op = self.gs_op
            if op is not None:  # W's diagonal blocks, already extracted (saves 9 sparse slices)
                rho = op.rho if op.order is None else op.rho[np.argsort(op.order)]
            else:
                rho = _res.rho_from_diagonal(_diagonal_of(self.W))
            self._scale_rho = (scale or _res.residual_scale(self.b, rho), rho)
        scale, rho = self._scale_rho
        return _res.residual(r, u, self.mu, rho, scale, law=law)

    def cone_violation(self, r):
        return _res.cone_violation(r, self.mu)


def _solve_assembled(W, b, mu, law, method, tol, max_iter, r0, options) -> SolveResult:
    t0 = time.perf_counter()
    target = _AssembledTarget(*_check_assembled(W, b, mu))
    return _solve(target, law, _resolve_method(law, method), tol, max_iter, r0, options, t0)


def _diagonal_of(W: sp.csr_matrix) -> np.ndarray:
    """(m, 3, 3) diagonal blocks of a sparse W."""
    m = W.shape[0] // 3
    out = np.empty((m, 3, 3))
    for a in range(3):
        for c in range(3):
            out[:, a, c] = W[a::3, c::3].diagonal()
    return out


def solve_socqp(W, b, mu, method: str = "gs", tol: float = 1e-8, max_iter: int | None = None, r0=None, **options) -> SolveResult:
    """min 1/2 r^T W r + b^T r  s.t. r_i in K_mu_i = {||r_T|| <= mu r_N}.

    W: scipy sparse (3m, 3m) symmetric PSD in 3x3 blocks, normal first in each block; b: (3m,);
    mu: scalar or (m,).  method: "gs" (block Gauss-Seidel + Anderson acceleration + subspace Newton steps), "apgd", "clarabel"
    (interior point, then Gauss-Seidel sweeps from its optimum until the residual is below tol), "auto"
    (= "gs").  tol: on the residual of residual.py (every method).  max_iter: the method's own budget
    (DEFAULT_MAX_ITER): Gauss-Seidel sweeps for gs and fixed_point (run_gauss_seidel's ``max_sweeps``, the
    CLI's --max-sweeps), iterations for apgd and clarabel.
    options: gs: anderson=8 (memory; 0 = no Anderson), anderson_start=10, newton=20 (subspace Newton steps on
    the faces the sweeps identified, tried at the residual checks from this sweep on; None = off, then with
    anderson=0 plain Gauss-Seidel), newton_every=10, newton_cg=(30, 200), omega=1.0, order="natural",
    symmetric=False (True: forward + backward sweeps; a residual: switch to them once there, run_gauss_seidel),
    check_every=10, time_limit, scale (replaces max_i rho_i ||b_i|| in the residual, e.g. to floor it),
    give_up (stop, status "stalled", once the run's rate projects more than give_up * max_iter sweeps:
    gauss_seidel.projected_sweeps), callback(sweeps, residual) at every residual check (also during
    clarabel's polish), stop(r, u) -> bool (the caller's own rule, asked at every check: True ends the run,
    status "certified"; e.g. certificate.error_bound below a tolerance);
    apgd: check_every, time_limit, callback, stop; clarabel: threads, linear_solver, time_limit, polish=True (False:
    return clarabel's own point, converged when clarabel reports Solved, whatever its residual)."""
    return _solve_assembled(W, b, mu, "soc", method, tol, max_iter, r0, dict(options))


def solve_coulomb(W, b, mu, method: str = "auto", tol: float = 1e-8, max_iter: int | None = None, r0=None, **options) -> SolveResult:
    """Coulomb friction u = W r + b, (u_i, r_i) in Coulomb's law (De Saxcé form) for every contact.

    Same arguments as solve_socqp.  method: "gs" (accelerated Gauss-Seidel on the law itself; it can
    cycle on strongly coupled problems), "fixed_point" (SOCQPs with s = mu ||u_T||, coulomb_fixed_point.py),
    "auto" (gs, switching to fixed_point if gs stalls for 200 sweeps).  gs option cluster=20 (the Coulomb law
    only): from that sweep on, the contacts over tol and those on their strands are solved together by
    Levenberg-Marquardt at the residual checks (cluster_newton.py; None = off), cluster_every=10."""
    return _solve_assembled(W, b, mu, "coulomb", method, tol, max_iter, r0, dict(options))


# ----------------------------------------------------------------------------------------------
# factored problem
# ----------------------------------------------------------------------------------------------
def sweep_costs(problem: ContactProblem) -> dict:
    """Per-sweep flop estimates of both Gauss-Seidel forms and the bytes of the assembled blocks.
    assembled: 18 flops per stored upper block; matrix_free: 6 per packed entry of H and of H D."""
    H = problem.packed_H()
    seg_ptr, _, h0, h1 = contact_segments(problem, H)
    k = np.diff(seg_ptr)
    n_blocks = int(np.sum(k * (k + 1) // 2)) + problem.n_contacts  # upper bound (diagonal counted twice)
    sizes = np.diff(problem.dof_offsets)
    seg_strand = np.repeat(np.arange(problem.n_strands), k)
    dense = np.array([d.ndim == 2 for d in problem.D_blocks], dtype=bool)
    g_entries = np.where(dense[seg_strand], sizes[seg_strand], (h1 - h0)).sum() if k.sum() else 0
    return {
        "assembled_flops": 18 * n_blocks,
        "matrix_free_flops": 6 * (H.cols.size + int(g_entries)),
        "assembled_bytes": 80 * n_blocks,
    }


ASSEMBLED_MIN_GAIN = 0.5  # "auto" assembles W only when a sweep then costs at most this fraction


def choose_form(problem: ContactProblem) -> str:
    """'assembled' when its sweep costs at most half the matrix-free one and its blocks fit
    ASSEMBLED_MEMORY_CAP, else 'matrix_free'.  Half, not merely less: assembling costs set-up time and
    about three times the blocks' memory at its peak, so a near tie goes matrix-free (harolongo with all
    contacts: flop ratio 0.88, 0.22 vs 0.25 s per sweep, but 13 s and 4 GB to assemble against 3 s; the
    30k bench problem: ratio 0.2, assembled)."""
    c = sweep_costs(problem)
    if c["assembled_bytes"] > ASSEMBLED_MEMORY_CAP:
        return "matrix_free"
    return "assembled" if c["assembled_flops"] <= ASSEMBLED_MIN_GAIN * c["matrix_free_flops"] else "matrix_free"


def _factored_residual(problem: ContactProblem, r, law: str, scale=None, u=None) -> float:
    """residual.py's residual of r, over the caller's ``scale`` when given (see run_gauss_seidel)."""
    if scale is None:
        return problem.residual(r, law=law, u=u)
    u = problem.velocity(r) if u is None else u
    return _res.residual(r, u, problem.mu, problem.rho(), float(scale), law=law)


class _FactoredTarget:
    """What the one dispatch (:func:`_solve`) needs from a ContactProblem (W = H D H^T + 2 gamma I)."""

    clarabel_form = "factored"
    polish_within_tol = False  # see _AssembledTarget

    def __init__(self, problem: ContactProblem, form: str):
        self.problem, self.b, self.mu = problem, problem.b, problem.mu
        self.requested_form = form
        self._form = None

    @property
    def form(self) -> str:
        """The operators' form: the caller's, or choose_form's for "auto" (decided once, when first needed)."""
        if self._form is None:
            self._form = choose_form(self.problem) if self.requested_form == "auto" else self.requested_form
        return self._form

    def gs_operator(self, order):
        order = _resolve_order(order, self.problem.H)
        if self.form == "assembled":
            return AssembledOperator.from_problem(self.problem, order)
        return MatrixFreeOperator(self.problem, order)

    def apgd_operator(self):
        """(x -> W x, rho, b)."""
        if self.form == "assembled":
            op = AssembledOperator.from_problem(self.problem)
            return UpperMatvec(op.W), op.rho, self.b
        return FactoredMatvec(self.problem), self.problem.rho(), self.b

    def clarabel(self, max_iter, options):
        return solve_factored(self.problem, max_iter=max_iter, **options)

    def polish_operator(self):
        if self.form == "assembled":
            return AssembledOperator.from_problem(self.problem)
        return MatrixFreeOperator(self.problem)

    def velocity(self, r):
        return self.problem.velocity(r)

    def residual(self, r, u, law, scale):
        return _factored_residual(self.problem, r, law, scale, u)

    def cone_violation(self, r):
        return self.problem.cone_violation(r)


def solve_contact_problem(
    problem: ContactProblem,
    law: str = "soc",
    method: str = "auto",
    tol: float = 1e-8,
    max_iter: int | None = None,
    r0=None,
    form: str = "auto",
    **options,
) -> SolveResult:
    """Solve u = (H D H^T + 2 gamma I) r + b under ``law`` ("soc": the SOCQP of the inversion;
    "coulomb": the forward simulator's friction) for a ContactProblem.

    method: SOC: "gs" | "apgd" | "clarabel" | "admm" | "auto" (= "gs"); Coulomb: "gs" | "fixed_point" | "auto"
    (see solve_coulomb).  form (gs, apgd, fixed_point): "assembled" (W in 3x3 blocks,
    assembled strand by strand), "matrix_free" (v = D H^T r kept per strand) or "auto" (choose_form).
    clarabel uses the sparse factored SOCQP (clarabel_socqp.py).  "admm" (SOC law, ContactProblem only):
    strand-split ADMM with one Cholesky factor per strand (admm.py; options beta, alpha, anderson, warm_sweeps,
    check_every, time_limit, scale, callback, stop), for contact-dense problems where Gauss-Seidel stalls
    (docs/solvers.md section 12).  Other options as in solve_socqp."""
    t0 = time.perf_counter()
    code = law_code(law)
    law = "soc" if code == 0 else "coulomb"
    method = _resolve_method(law, method)
    if form not in ("auto", "assembled", "matrix_free"):
        raise ValueError(f"unknown form {form!r}")
    return _solve(_FactoredTarget(problem, form), law, method, tol, max_iter, r0, dict(options), t0)


# ----------------------------------------------------------------------------------------------
# the one dispatch
# ----------------------------------------------------------------------------------------------
def _solve(target, law: str, method: str, tol: float, max_iter, r0, options: dict, t0: float) -> SolveResult:
    """Run ``method`` (resolved) on an _AssembledTarget or a _FactoredTarget; ``options`` is the caller's
    copy (this pops what it consumes)."""
    max_iter = DEFAULT_MAX_ITER.get(method, 5000) if max_iter is None else int(max_iter)
    info: dict = {}
    scale = options.get("scale")
    if method == "clarabel":
        polish = options.pop("polish", True)
        callback = options.pop("callback", None)
        out = target.clarabel(max_iter, {k: v for k, v in options.items() if k != "scale"})
        r, iters, status = out.r, out.iterations, out.status
        conv = status == "Solved"
        info.update(form=target.clarabel_form, setup_s=out.setup_s, solve_s=out.solve_s, kkt_size=out.kkt_size)
        if polish and status in ("Solved", "AlmostSolved"):
            residual = target.residual(r, target.velocity(r), law, scale)
            if residual > tol or target.polish_within_tol:
                r, conv, status = _polish_with_gs(target.polish_operator(), r, residual, tol, info, status,
                                                  callback, scale)
    else:
        order = options.pop("order", None)  # Gauss-Seidel's sweep order; APGD and ADMM have none
        if method == "admm":
            if not isinstance(target, _FactoredTarget):
                raise ValueError("method 'admm' splits W = H D H^T + 2 gamma I by strand: it needs a ContactProblem "
                                 "(solve_contact_problem), not an assembled W")
            out = run_admm(target.problem, tol=tol, max_iter=max_iter, r0=r0, **options)
            setup_s = out.setup_s
            info.update(solve_s=out.solve_s, history=out.history, anderson_restarts=out.anderson_restarts,
                        warm_sweeps=out.warm_sweeps)
            if out.stopped_by_rule:  # the caller's stop rule accepted r (status "certified")
                info["stopped_by"] = "stop"
            r, iters, conv, res_solver = out.r, out.iterations, out.converged, out.residual
        elif method == "apgd":
            mv, rho, b = target.apgd_operator()
            setup_s = time.perf_counter() - t0
            out = run_apgd(mv, b, target.mu, rho, tol=tol, max_iter=max_iter, r0=r0, **options)
            info.update(restarts=out.restarts, solve_s=out.solve_s, history=out.history)
            if out.stopped_by_rule:  # the caller's stop rule accepted r (status "certified")
                info["stopped_by"] = "stop"
            r, iters, conv, res_solver = out.r, out.iterations, out.converged, out.residual
        else:
            op = target.gs_operator(order)
            setup_s = time.perf_counter() - t0
            r, iters, conv, res_solver = _run_gs_family(op, law, method, tol, max_iter, r0, options, info)
        status = _iterative_status(conv, res_solver, iters, max_iter, info)
        info.update(form="strand_split" if method == "admm" else target.form, setup_s=setup_s)
    u = target.velocity(r)
    residual = target.residual(r, u, law, scale)
    return SolveResult(
        r=r, status=status, converged=bool(conv), residual=float(residual), iterations=int(iters),
        objective=float(0.5 * r @ (u + target.b)), cone_violation=target.cone_violation(r),
        time_s=time.perf_counter() - t0, method=method, info=info,
    )
