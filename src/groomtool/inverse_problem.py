"""The inverse problem: rest curvatures q0 that make the groomed shape an equilibrium (docs/maths.md section 7).

Isolated strands:   K (q - q0) = F(q)                 =>  q0 = q - K^-1 F(q)
With contacts:      K (q - q0) = F(q) + H^T r, r_i in K_mu (Coulomb cones), under-determined; take

    min_r 1/2 || q - K^-1 (H^T r + F) - q0_guess ||^2 + gamma_abs ||r||^2,   r_i in K_mu
    q0 = q - K^-1 (F + H^T r)

a second-order-cone QP  min 1/2 r^T W r + b^T r  with W = H K^-2 H^T + 2 gamma_abs I,
b = -H K^-1 d, d = q - K^-1 F - q0_guess.  ``gamma`` is given relative to the mean diagonal of
H K^-2 H^T (gamma_abs = gamma * mean diag), so it is dimensionless.

Here: K, F and q0 of isolated strands, the scaled SOCQP (:class:`InverseProblem`), its solve with the
solver that solver_choice.py picks (:func:`solve_inverse_problem`), q0 from the forces, the
certified distance of q0 to the optimum's and the equilibrium check.  The whole job (fit, contacts,
stabilisation, report) is invert.py's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit

from .material import Material
from .rods import clothoid as cl
from .rods import superhelix as sh
from .solver_choice import AUTO_CLARABEL_MAX_CONTACTS, GS_GIVE_UP, choose_solver, dense_iterative_method
from .timing import progress


MODELS = ("superhelix", "clothoid")


def model_name(rod) -> str:
    """"clothoid" for a :class:`~groomtool.rods.clothoid.SuperClothoid`, else "superhelix"."""
    return "clothoid" if isinstance(rod, cl.SuperClothoid) else "superhelix"


def rod_module(rod):
    """The rod model's module (:mod:`groomtool.rods.clothoid` or :mod:`groomtool.rods.superhelix`)."""
    return cl if isinstance(rod, cl.SuperClothoid) else sh


def _factor(stiffness_factor, S):
    return np.ones(S) if stiffness_factor is None else np.asarray(stiffness_factor, dtype=np.float64).reshape(-1)


def strand_stiffness(helix, material: Material, stiffness_factor=None):
    """Super-Helix: K (S, N, 3): K_j = f_s l_j (GJ, EI, EI), f_s the strand's stiffness factor (None: all 1), 0 on
    padding.  Super Space Clothoid: K in banded form (diagonal blocks (S, N + 1, 3), off-diagonal blocks (S, N, 3),
    :func:`groomtool.rods.clothoid.stiffness`) times f_s."""
    if isinstance(helix, cl.SuperClothoid):
        diag, off = cl.stiffness(helix, material.stiffness_diag)
        f = _factor(stiffness_factor, helix.n_strands)
        return diag * f[:, None, None], off * f[:, None, None]
    K = sh.stiffness(helix, material.stiffness_diag)
    if stiffness_factor is not None:
        K = K * np.asarray(stiffness_factor, dtype=np.float64).reshape(-1, 1, 1)
    return K


def stiffness_apply(helix, material: Material, d: np.ndarray, stiffness_factor=None) -> np.ndarray:
    """K d for d shaped like the curvatures (diagonal K of the helix, block tridiagonal of the clothoid)."""
    if isinstance(helix, cl.SuperClothoid):
        f = _factor(stiffness_factor, helix.n_strands)
        return cl.stiffness_apply(helix, material.stiffness_diag, d) * f[:, None, None]
    return strand_stiffness(helix, material, stiffness_factor) * d


def stiffness_solve(helix, material: Material, rhs: np.ndarray, stiffness_factor=None) -> np.ndarray:
    """K^-1 rhs for rhs shaped like the curvatures; 0 on padding."""
    if isinstance(helix, cl.SuperClothoid):
        f = _factor(stiffness_factor, helix.n_strands)
        return cl.stiffness_solve(helix, material.stiffness_diag, rhs) / f[:, None, None]
    K = strand_stiffness(helix, material, stiffness_factor)
    return np.divide(rhs, K, out=np.zeros_like(rhs), where=K > 0)


def isolated_rest_curvatures(helix, material: Material, gravity, kin=None,
                             stiffness_factor=None) -> np.ndarray:
    """q0 = q - K^-1 F(q), (S, N, 3) (clothoid: (S, N + 1, 3), a tridiagonal solve per strand); padding stays 0."""
    F = gravity_force(helix, material, gravity, kin)
    return helix.curvatures - stiffness_solve(helix, material, F, stiffness_factor)


def map_rod_chunks(rod, fn, chunk: int = 1024) -> np.ndarray:
    """:func:`groomtool.rods.superhelix.map_strand_chunks` for either model: ``fn(sub) -> (s, n, ...)`` per group
    of strands of similar element counts, gathered shaped like the curvatures."""
    if not isinstance(rod, cl.SuperClothoid):
        return sh.map_strand_chunks(rod, fn, chunk)
    order = np.argsort(rod.n_elements, kind="stable")
    out = np.zeros(rod.curvatures.shape)
    for start in range(0, rod.n_strands, chunk):
        ids = order[start:start + chunk]
        part = fn(rod.subset(ids))
        out[ids, :part.shape[1]] = part
    return out


def gravity_force(helix, material: Material, gravity, kin=None) -> np.ndarray:
    """F(q) (S, N, 3) (clothoid: (S, N + 1, 3)): with ``kin`` given, from it; else in chunks of strands of similar
    length."""
    mod = rod_module(helix)
    if kin is not None:
        return mod.gravity_force(helix, material.linear_density, gravity, kin)
    return map_rod_chunks(helix, lambda sub: mod.gravity_force(sub, material.linear_density, gravity))


def rest_curvature_guess(helix: sh.SuperHelix, guess: str) -> np.ndarray:
    """q0_guess: ``current`` = q (keep the least elastic energy: contacts carry what they can);
    ``tip`` = the curvature of each strand's last element everywhere (the tip carries no load,
    so its shape is its natural shape; the lecture's q0 = q(L), for uniformly curled hair)."""
    if guess == "current":
        return helix.curvatures.copy()
    if isinstance(helix, cl.SuperClothoid):  # the tip node
        tip = helix.curvatures[np.arange(helix.n_strands), helix.n_elements]
        return np.where(helix.node_mask[..., None], tip[:, None, :], 0.0)
    last = np.maximum(helix.n_elements - 1, 0)
    tip = helix.curvatures[np.arange(helix.n_strands), last]
    return np.where(helix.element_mask[..., None], tip[:, None, :], 0.0)


def equilibrium_residuals(helix: sh.SuperHelix, rest_curvatures, material: Material, gravity,
                          contacts=None, forces=None, chunk: int = 1024, stiffness_factor=None) -> np.ndarray:
    """||K (q - q0) - F - H^T r|| / ||F|| per strand (K with the per-strand ``stiffness_factor``; either model), recomputed
    from scratch (fresh kinematics, H^T r point by point), independent of how q0 was obtained.  In chunks of
    strands of similar length, each chunk's kinematics serving both F and H^T r."""
    from .contact.jacobian import point_forces_generalized  # contact (0.3 s): kept off the CLI's start

    S = helix.n_strands
    F = np.zeros(helix.curvatures.shape)
    HtR = None
    if contacts is not None and forces is not None and len(forces):
        # the point forces: F_i^T r_i at s_a on strand a, its opposite at s_b on strand b
        frames = np.asarray(contacts.frame, dtype=np.float64).reshape(-1, 3, 3)
        world = np.einsum("pji,pj->pi", frames, np.asarray(forces, dtype=np.float64).reshape(-1, 3))
        strand = np.concatenate([np.asarray(contacts.strand_a, dtype=np.int64),
                                 np.asarray(contacts.strand_b, dtype=np.int64)])
        arc = np.concatenate([np.asarray(contacts.s_a, dtype=np.float64),
                              np.asarray(contacts.s_b, dtype=np.float64)])
        keep = strand >= 0
        strand, arc, point_force = strand[keep], arc[keep], np.concatenate([world, -world])[keep]
        HtR = np.zeros(helix.curvatures.shape)
    order = np.argsort(helix.n_elements, kind="stable")
    which_chunk = np.empty(S, dtype=np.int64)
    local = np.empty(S, dtype=np.int64)
    for c, start in enumerate(range(0, S, chunk)):
        which_chunk[order[start:start + chunk]] = c
        local[order[start:start + chunk]] = np.arange(len(order[start:start + chunk]))
    if HtR is not None:
        by_chunk = np.argsort(which_chunk[strand], kind="stable")
        bounds = np.searchsorted(which_chunk[strand][by_chunk], np.arange((S + chunk - 1) // chunk + 1))
    mod = rod_module(helix)
    for c, start in enumerate(range(0, S, chunk)):
        ids = order[start:start + chunk]
        sub = helix.subset(ids)
        kin = mod.kinematics(sub)
        n = sub.curvatures.shape[1]
        F[ids, :n] = mod.gravity_force(sub, material.linear_density, gravity, kin)
        if HtR is not None:
            mine = by_chunk[bounds[c]:bounds[c + 1]]
            HtR[ids, :n] = point_forces_generalized(sub, kin, local[strand[mine]], arc[mine], point_force[mine])
    res = stiffness_apply(helix, material, helix.curvatures - rest_curvatures, stiffness_factor) - F
    if HtR is not None:
        res -= HtR
    num = np.linalg.norm(res.reshape(S, -1), axis=1)
    den = np.linalg.norm(F.reshape(S, -1), axis=1)
    return num / np.maximum(den, np.finfo(float).tiny)


@dataclass
class InverseProblem:
    """The inverse SOCQP in solver units: W~ = H (K^-2 / w_scale) H^T + 2 gamma I, b~ = b / (w_scale f_scale),
    r = f_scale r~.  ``H`` and ``inv_stiffness`` (flat K^-1) are kept to map r back to q0.  For the Super Space
    Clothoid K is block tridiagonal, not diagonal: ``inv_stiffness`` is None, ``inv_apply`` applies K^-1 to flat
    vectors (tridiagonal solves) and ``inv_square_blocks`` holds the dense K^-2 of every strand (its real dofs)."""

    H: object
    inv_stiffness: np.ndarray | None
    d: np.ndarray
    gamma: float
    w_scale: float
    f_scale: float
    b: np.ndarray
    mu: np.ndarray
    q0_free: np.ndarray | None = None  # flat q - K^-1 F: q0 = q0_free - K^-1 H^T r
    inv_apply: object = None  # clothoid: flat x -> flat K^-1 x
    inv_square_blocks: list | None = None  # clothoid: per strand dense K^-2

    def apply_inverse_stiffness(self, x: np.ndarray) -> np.ndarray:
        """K^-1 x for a flat x."""
        return self.inv_stiffness * x if self.inv_apply is None else self.inv_apply(x)

    def contact_problem(self, helix: sh.SuperHelix):
        """The solvers' ContactProblem: W~ = H D H^T + 2 gamma I with D = K^-2 / w_scale per strand of
        ``helix``.  Super-Helix: D is diagonal and passed as one flat array (per-strand dense diagonal matrices,
        as before, cost ~1 GB on harolongo only to be recognised as diagonal); clothoid: dense blocks."""
        from .solvers import ContactProblem  # kept off the CLI's start

        D = (self.inv_stiffness ** 2 / self.w_scale if self.inv_square_blocks is None
             else [blk / self.w_scale for blk in self.inv_square_blocks])
        return ContactProblem(H=self.H, D_blocks=D,
                              dof_offsets=3 * helix.flat_offsets(), gamma=self.gamma, b=self.b, mu=self.mu)

    def objective(self, r: np.ndarray) -> float:
        """1/2 || K^-1 H^T r - d ||^2 + gamma_abs ||r||^2 in physical units (r in newtons)."""
        y = self.apply_inverse_stiffness(self.H.T @ r) - self.d
        return 0.5 * float(y @ y) + self.gamma * self.w_scale * float(r @ r)


@njit(cache=True)
def _row_sums_of_squares(indptr, indices, data, scale):
    """sum_j (H_ij scale_j)^2 per row of a CSR H (the diagonal of H diag(scale)^2 H^T)."""
    out = np.zeros(indptr.shape[0] - 1)
    for i in range(out.shape[0]):
        acc = 0.0
        for p in range(indptr[i], indptr[i + 1]):
            v = data[p] * scale[indices[p]]
            acc += v * v
        out[i] = acc
    return out


def build_inverse_problem(helix, F, H, material: Material, gravity, guess: str, gamma: float,
                          mu: np.ndarray, stiffness_factor=None) -> InverseProblem:
    """The scaled SOCQP for gravity forces F (S, N, 3) and contact Jacobian H (K with the per-strand
    ``stiffness_factor``, None: the material's)."""
    if isinstance(helix, cl.SuperClothoid):
        return _build_clothoid_problem(helix, F, H, material, gravity, guess, gamma, mu, stiffness_factor)
    K = strand_stiffness(helix, material, stiffness_factor)
    q0_guess = rest_curvature_guess(helix, guess)
    inv_k = helix.to_flat(np.divide(1.0, K, out=np.zeros_like(K), where=K > 0)).ravel()
    q = helix.to_flat(helix.curvatures).ravel()
    d = q - inv_k * helix.to_flat(F).ravel() - helix.to_flat(q0_guess).ravel()
    # diag(H K^-2 H^T) and b = -H K^-1 d without forming H K^-1 (on harolongo H alone is 1.2 GB)
    H = sp.csr_matrix(H)
    diag = _row_sums_of_squares(H.indptr, H.indices, H.data, inv_k)
    w_scale = float(diag.mean()) if len(diag) and diag.mean() > 0 else 1.0
    b = -(H @ (inv_k * d))
    f_scale = material.linear_density * np.linalg.norm(gravity) * float(np.mean(helix.strand_lengths))
    b_scaled = b / (w_scale * f_scale)
    return InverseProblem(H=H, inv_stiffness=inv_k, d=d, gamma=gamma, w_scale=w_scale, f_scale=f_scale,
                          b=b_scaled, mu=np.asarray(mu, dtype=np.float64),
                          q0_free=helix.to_flat(q0_guess).ravel() + d)


def clothoid_inverse_square_blocks(clothoid: cl.SuperClothoid, material: Material, stiffness_factor=None,
                                   chunk: int = 256, strands=None) -> list:
    """Per strand the dense K^-2 over its real dofs (3 (N_s + 1) square, node-major like the flat dofs); only for
    ``strands`` when given (the others get a unit diagonal: for strands no contact touches, H has no entry in their
    columns and D does not enter W = H D H^T)."""
    f = _factor(stiffness_factor, clothoid.n_strands)
    out = [np.ones(3 * (int(n) + 1)) for n in clothoid.n_elements]
    order = np.argsort(clothoid.n_elements, kind="stable")
    if strands is not None:
        order = order[np.isin(order, strands)]
    for start in range(0, len(order), chunk):
        ids = order[start:start + chunk]
        sub = clothoid.subset(ids)
        K = cl.stiffness_matrix(sub, material.stiffness_diag) * f[ids, None, None]
        real = np.repeat(sub.node_mask, 3, axis=1)
        K = np.where(real[:, :, None] & real[:, None, :], K, 0.0) + (~real)[:, :, None] * np.eye(real.shape[1])
        inv = np.linalg.inv(K)
        sq = inv @ inv
        for i, s in enumerate(ids):
            n = 3 * (int(sub.n_elements[i]) + 1)
            out[s] = np.ascontiguousarray(sq[i, :n, :n])
    return out


def _build_clothoid_problem(rod: cl.SuperClothoid, F, H, material: Material, gravity, guess: str, gamma: float,
                            mu: np.ndarray, stiffness_factor=None) -> InverseProblem:
    """:func:`build_inverse_problem` for the Super Space Clothoid: K^-1 by tridiagonal solves, K^-2 dense per strand
    (the solvers take dense D blocks), diag(H K^-2 H^T) from the solvers' own diagonal blocks of W."""
    from .solvers import ContactProblem  # kept off the CLI's start

    def inv_apply(x):
        return rod.to_flat(stiffness_solve(rod, material, rod.from_flat(np.asarray(x).reshape(-1, 3)),
                                           stiffness_factor)).ravel()

    q0_guess = rest_curvature_guess(rod, guess)
    q = rod.to_flat(rod.curvatures).ravel()
    d = q - inv_apply(rod.to_flat(F).ravel()) - rod.to_flat(q0_guess).ravel()
    H = sp.csr_matrix(H)
    # dense K^-2 only where a contact touches the strand (harolongo's head contacts: a few thousand of 7,905 strands)
    col_strand = np.repeat(np.arange(rod.n_strands), 3 * (rod.n_elements + 1))
    touched = np.unique(col_strand[H.indices]) if H.nnz else np.zeros(0, np.int64)
    blocks = clothoid_inverse_square_blocks(rod, material, stiffness_factor, strands=touched)
    m = H.shape[0] // 3
    diag = np.zeros(0)
    if m:
        probe = ContactProblem(H=H, D_blocks=blocks, dof_offsets=3 * rod.flat_offsets(), gamma=0.0,
                               b=np.zeros(H.shape[0]), mu=np.zeros(m))
        diag = np.einsum("kii->ki", probe.diagonal_blocks()).ravel()
        del probe
    w_scale = float(diag.mean()) if len(diag) and diag.mean() > 0 else 1.0
    b = -(H @ inv_apply(d))
    f_scale = material.linear_density * np.linalg.norm(gravity) * float(np.mean(rod.strand_lengths))
    return InverseProblem(H=H, inv_stiffness=None, d=d, gamma=gamma, w_scale=w_scale, f_scale=f_scale,
                          b=b / (w_scale * f_scale), mu=np.asarray(mu, dtype=np.float64),
                          q0_free=rod.to_flat(q0_guess).ravel() + d, inv_apply=inv_apply,
                          inv_square_blocks=blocks)


def rest_curvatures_with_contacts(helix, material, F, H, forces_flat, stiffness_factor=None) -> np.ndarray:
    """q0 = q - K^-1 (F + H^T r), shaped like the curvatures, F the gravity forces (the same shape)."""
    HtR = helix.from_flat((H.T @ forces_flat).reshape(-1, 3))
    return helix.curvatures - stiffness_solve(helix, material, F + HtR, stiffness_factor)


def cone_violation(forces: np.ndarray, mu: np.ndarray) -> float:
    """max over contacts of max(0, ||r_T|| - mu r_N) (newtons), 0 for no contact."""
    if len(forces) == 0:
        return 0.0
    f = forces.reshape(-1, 3)
    return float(np.max(np.maximum(0.0, np.linalg.norm(f[:, 1:], axis=1) - mu * f[:, 0])))


def rest_curvature_error_bound(problem: InverseProblem, cp, r, u=None, line_search: bool = True,
                               strands=None, HTr=None, strands_c=None, products: dict | None = None) -> dict:
    """Certified bound on how far the rest curvatures of forces r (solver units, (3m,), in their cones) are
    from those of the optimum r*:  |q0 - q0*| = f_scale |K^-1 H^T (r - r*)| = f_scale sqrt(w_scale) |A^T (r - r*)|
    (A = H D^1/2, D = K^-2 / w_scale) <= f_scale sqrt(w_scale) B  (solvers/certificate.py), with B the smaller of

      * "forces":  B = sqrt(G(r, l = A^T r)) (+ the line search of error_bound, diagonal D), G the duality gap;
      * "strands" (with ``strands`` = h (n,), e.g. the strand-split ADMM's sum_e J_e^T x_e):
        B = (delta + sqrt(4 G(r, l) - delta^2)) / 2 at l = D^1/2 h, delta = |A^T r - l|
        (certificate.error_bound_with_strands; any D, through D_apply).

    Both are upper bounds on the same |A^T (r - r*)| for the same r: g(l) <= f* for every dual point l (weak
    duality), f(r) - f* >= |A^T (r - r*)|^2 / 2 and f* - g(l) >= |l - A^T r*|^2 / 2, so G(r, l) = f(r) - g(l)
    bounds |A^T (r - r*)| through the formula above at ANY l; the minimum of two valid bounds is one.  The
    relative bound below is increasing in the absolute one, so it is the smaller one too.
    Returns {"q0_error_bound": relative to |q0*| (>= |q0| - the bound; inf when that is not positive),
    "q0_error_bound_abs": 1/m, l2 over all dofs, "q0_norm": |q0|, "q0_bound_source": "forces" | "strands"}.
    ``cp``: problem.contact_problem(helix); ``u``: W r + b, ``HTr``: H^T r, ``strands_c``: H D h + b, when already
    known (e.g. through the strand-split ADMM's generators, admm_structured.StructuredSplit.check_products);
    ``products`` (a dict): gets the H^T r and H D h + b used, for a later call on the same r and h."""
    from .solvers.certificate import error_bound, error_bound_with_strands  # kept off the CLI's start

    e = error_bound(cp, r, u, line_search=line_search, HTr=HTr)
    best, source = e["bound"], "forces"
    if products is not None:
        products["HTr"] = e["HTr"]
    if strands is not None:
        if strands_c is None:
            strands_c = cp.H @ cp.D_apply(np.asarray(strands, dtype=np.float64).reshape(-1)) + cp.b
        if products is not None:
            products["strands_c"] = strands_c
        e2 = error_bound_with_strands(cp, r, strands, HTr=e["HTr"], c=strands_c)
        if e2["bound"] < best:
            best, source = e2["bound"], "strands"
    absolute = problem.f_scale * math.sqrt(problem.w_scale) * best
    q0 = problem.q0_free - problem.apply_inverse_stiffness(problem.f_scale * e["HTr"])
    q0_norm = float(np.linalg.norm(q0))
    rel = absolute / (q0_norm - absolute) if q0_norm > absolute else math.inf
    return {"q0_error_bound": float(rel), "q0_error_bound_abs": float(absolute), "q0_norm": q0_norm,
            "q0_bound_source": source}


def admm_geometry(helix, contacts, kin=None):
    """What the strand-split ADMM needs besides the ContactProblem to solve its strand systems in O(elements)
    (solvers.admm_structured.HelixContacts: the Super-Helix groom, the contacts H was built from, the kinematics), or
    None for a Super Space Clothoid (dense D blocks: the dense strand factors) or without contacts."""
    if contacts is None or isinstance(helix, cl.SuperClothoid):
        return None
    from .solvers.admm_structured import HelixContacts  # the solvers: kept off the CLI's start

    return HelixContacts(helix, contacts, kin)


def solver_method(cp, params, redundant_fraction: float = 1.0, geometry=None) -> str:
    """The solver solve_inverse_problem runs on the ContactProblem ``cp`` (params.solver; ``auto``: choose_solver, then
    on dense contacts beyond 10,000 the strand-split ADMM where it fits, solver_choice.dense_iterative_method;
    ``geometry``: admm_geometry's, the structured strand factors' memory counted instead of dense ones)."""
    method = choose_solver(params.solver, cp.n_contacts, redundant_fraction)
    if params.solver == "auto" and method == "gs":  # dense contacts beyond clarabel's reach: the strand-split ADMM
        method = dense_iterative_method(cp, redundant_fraction, structured=_structured(cp, geometry))
    return method


def _structured(cp, geometry) -> bool:
    if geometry is None:
        return False
    from .solvers.admm_structured import applies  # the solvers: kept off the CLI's start

    return applies(cp, geometry)


def solve_inverse_problem(problem: InverseProblem, helix: sh.SuperHelix, params, quiet: bool = True,
                          redundant_fraction: float = 1.0, initial_forces=None, initial_state=None, cp=None,
                          geometry=None) -> dict:
    """Solve the scaled SOCQP with the chosen solver; forces returned in newtons (m, 3).  ``params``: the
    InversionParams (solver, solver_tolerance, max_sweeps, q0_tolerance).  The progress bar counts
    Gauss-Seidel sweeps (clarabel's polish included; ADMM iterations) and shows the residual.  ``auto``: choose_solver,
    then on dense contacts beyond 10,000 the strand-split ADMM (solver_choice.dense_iterative_method); if
    its Gauss-Seidel does not converge on at most 10,000 contacts, clarabel takes over (report:
    fallback_from).  ``initial_forces`` (m, 3) in newtons, e.g. the previous stabilisation round's:
    Gauss-Seidel starts from them (clarabel ignores them).  The strand-split ADMM returns its end state as
    ``admm_state`` (opaque; None for the other solvers); given back as ``initial_state`` on a problem with the same
    contacts (the same H: another K, as after stiffening), ADMM starts from it instead of ``initial_forces`` (its
    multipliers carried over, rescaled for the new K: admm.ADMMState); the other solvers ignore it.  ``cp``: the
    problem's ContactProblem when the caller built it already (problem.contact_problem(helix)).  ``geometry``
    (admm_geometry(helix, contacts, kin)): ADMM solves its strand systems through their semiseparable factors
    (solvers/admm_structured.py, O(elements + ends) per iteration instead of O(n_s^2) per strand)."""
    from .solvers import solve_contact_problem  # the solvers (clarabel, 0.3 s): kept off the CLI's start
    from .solvers.gauss_seidel import GIVE_UP_MIN_SWEEPS, give_up_projection, projected_sweeps

    if cp is None:
        cp = problem.contact_problem(helix)
    m = len(problem.mu)
    method = solver_method(cp, params, redundant_fraction, geometry)
    bounded = problem.gamma > 0 and problem.q0_free is not None
    gave_up = {}  # ADMM: the projection of its q0 bound that stopped it (give_up_projection on the bound's history)
    admm_state = {}  # ADMM: its end state ("state"), for a later solve's initial_state
    last_strands = {}  # ADMM: the last strand solves' h = sum_e J_e^T x_e its stop rule saw (a dual point)

    def run(method):
        with progress(params.max_sweeps, f"contact solve ({method}, {m:,} contacts)", quiet,
                      unit="sweep", budget=True) as bar:
            shown = {"residual": math.nan, "q0": math.nan, "sweeps": 0, "history": []}

            def postfix():
                text = f"residual {shown['residual']:.1e} (target {params.solver_tolerance:.0e})"
                if math.isfinite(shown["q0"]):
                    text += f", q0 within {shown['q0']:.1e}"
                    if params.q0_tolerance is not None:
                        text += f" (target {params.q0_tolerance:.0e}"
                        # at the bound's own rate over the second half of the run (as give_up projects)
                        need = projected_sweeps(shown["history"], params.q0_tolerance) if len(shown["history"]) > 2 \
                            else math.nan
                        if math.isfinite(need) and need > shown["sweeps"]:
                            text += f", ~{need - shown['sweeps']:,.0f} more sweeps at this rate"
                        text += ")"
                bar.set_postfix_str(text)

            def show(sweeps, residual):
                bar.update(max(0, min(sweeps, bar.total) - bar.n))
                shown["residual"] = residual
                shown["sweeps"] = sweeps
                postfix()

            def stop(r, u, strands=None, HTr=None, c=None):
                """The certified rest-curvature error: shown, and a stop rule (q0_tolerance).  ADMM's ``HTr`` and
                ``c`` (its generators' H^T r and H D h + b, run_admm(stop_products=True)); without them the products
                are H's, and are kept with r for the final certificate."""
                if strands is not None:  # ADMM's strand solves h: a second dual point (rest_curvature_error_bound)
                    last_strands["h"] = strands
                products = {} if HTr is None else None
                if products is not None and strands is not None:
                    # the forces as they will be returned (projected as below, bit for bit), so that the final
                    # certificate can reuse this check's products with H
                    from .solvers.certificate import project_forces  # kept off the CLI's start

                    r, moved = project_forces(r, problem.mu)
                    if moved > 0.0:
                        u = None
                shown["q0"] = rest_curvature_error_bound(problem, cp, r, u, line_search=False, strands=strands,
                                                         HTr=HTr, strands_c=c, products=products)["q0_error_bound"]
                if products is not None and strands is not None:
                    last_strands["checked"] = (r, u, strands, products)
                if math.isfinite(shown["q0"]):
                    history = shown["history"]
                    if history and history[-1][0] == shown["sweeps"]:  # the same check redone with H (run_admm)
                        history.pop()
                    history.append((shown["sweeps"], shown["q0"]))
                postfix()
                if params.q0_tolerance is None:
                    return False
                if shown["q0"] <= params.q0_tolerance:
                    return True
                if method == "admm":  # Gauss-Seidel's give_up, on the certified bound's rate instead of the residual's
                    projected = give_up_projection(shown["history"], params.q0_tolerance, GS_GIVE_UP * params.max_sweeps,
                                                   max(GIVE_UP_MIN_SWEEPS, params.max_sweeps // 4)) \
                        if shown["history"] else None
                    if projected is not None:
                        gave_up["projected"] = projected
                        return True
                return False

            # the sweep budget (and giving up on it early) is Gauss-Seidel's; clarabel keeps its own iteration limit
            gs_only = {} if method == "clarabel" else {"max_iter": params.max_sweeps}
            if method == "gs":
                gs_only["give_up"] = GS_GIVE_UP
            if method != "clarabel" and initial_forces is not None:
                gs_only["r0"] = np.asarray(initial_forces, dtype=np.float64).reshape(-1) / problem.f_scale
            if method == "admm":
                gs_only["stop_strands"] = True
                gs_only["stop_products"] = True
                gs_only["state_out"] = admm_state
                if initial_state is not None:
                    gs_only["initial_state"] = initial_state
                if geometry is not None:
                    gs_only["geometry"] = geometry
            if method != "clarabel" and bounded and (params.q0_tolerance is not None or not quiet):
                gs_only["stop"] = stop
            return solve_contact_problem(cp, law="soc", method=method, tol=params.solver_tolerance, callback=show,
                                         **gs_only)

    res = run(method)
    fallback = None
    if (params.solver == "auto" and method == "gs" and not res.converged and res.status != "certified"
            and m <= AUTO_CLARABEL_MAX_CONTACTS):
        fallback = {"solver": "gs", "status": str(res.status), "iterations": int(res.iterations),
                    "residual": float(res.residual), "time_s": float(res.time_s)}
        res = run("clarabel")
    # the forces, projected onto their cones (a round-off move for a solver's point): with any forces in their
    # cones q0 = q - K^-1 (F + H^T r) is an exact equilibrium, so even an unconverged solve is usable
    r = np.asarray(res.r, dtype=np.float64).reshape(-1)
    feasible = bool(np.all(np.isfinite(r)))
    moved = 0.0
    if feasible:
        from .solvers.certificate import project_forces  # kept off the CLI's start

        r, moved = project_forces(r, problem.mu)
    forces = r.reshape(-1, 3) * problem.f_scale
    # solved: the residual reached solver_tolerance, or (Gauss-Seidel's "certified") the certified rest-curvature
    # error reached q0_tolerance first ("stopped_on" says which)
    certified = res.status == "certified" and not gave_up
    converged = bool(res.converged) or certified
    status = "solved" if converged else ("stalled" if gave_up else str(res.status))
    out = {"forces": forces, "solver": res.method, "status": status, "converged": converged,
           "feasible": feasible, "iterations": int(res.iterations), "residual": float(res.residual),
           "time_s": float(res.time_s), "projected_by": float(moved * problem.f_scale)}
    if converged:
        out["stopped_on"] = "residual" if res.converged else "q0_tolerance"
    if feasible and bounded:
        # ADMM: also from its last strand solves (any dual point certifies r, even one a few iterations old)
        h = last_strands.get("h") if res.method == "admm" else None
        known = {}
        checked = last_strands.get("checked") if h is not None else None
        if checked is not None and checked[2] is h and np.array_equal(checked[0], r):
            # the forces and strand sums of the run's last check with H (the one that stopped it): its products
            known = {"u": checked[1], "HTr": checked[3]["HTr"], "strands_c": checked[3]["strands_c"]}
        bound = rest_curvature_error_bound(problem, cp, r, strands=h, **known)
        out["q0_error_bound"] = bound["q0_error_bound"]
        out["q0_error_bound_abs"] = bound["q0_error_bound_abs"]
        out["q0_bound_source"] = bound["q0_bound_source"]
    else:
        out["q0_error_bound"] = None
        out["q0_error_bound_note"] = ("no bound: gamma = 0 (the dual is not strongly concave)" if feasible
                                      else "no bound: the forces are not finite")
    if res.info.get("projected_sweeps") is not None:
        out["projected_sweeps"] = float(res.info["projected_sweeps"])
    if gave_up:  # ADMM stopped early: its q0 bound would reach q0_tolerance only far beyond the budget
        out["projected_sweeps"] = float(gave_up["projected"])
    if "polish_sweeps" in res.info:  # clarabel's point finished by Gauss-Seidel (solvers.api)
        out["polish_sweeps"] = int(res.info["polish_sweeps"])
        out["clarabel_residual"] = float(res.info["clarabel_residual"])
    if fallback is not None:
        out["fallback_from"] = fallback
        out["time_s"] += fallback["time_s"]
    out["redundant_strand_fraction"] = float(redundant_fraction)
    out["admm_state"] = admm_state.get("state") if res.method == "admm" else None
    return out

