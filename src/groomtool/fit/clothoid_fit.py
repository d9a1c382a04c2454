"""Production fit of Super Space Clothoids: polylines -> G2 piecewise clothoids within the fit tolerance,
with an adaptive element count, batched over strands (docs/clothoid.md, "Fitting").

Per strand:

1. the floating-tangent Super-Helix fit (:func:`groomtool.fit.fitter.fit_groom`, within the same tolerance)
   gives a piecewise-constant Darboux vector Omega_h(s) on [0, L_h], the root position and the root frame;
2. on N equal elements of [0, L_h] the nodal values q start as the L2 projection of Omega_h onto the hat
   functions (M_FE q = int N_i Omega_h, the integral by 32 midpoints per element, M_FE tridiagonal);
3. Levenberg-Marquardt (Marquardt's diagonal scaling, a damping per strand) on
   sum_v |C(lambda L_h u_v) - x_v|^2 over q, a rotation of the root frame about its normals n1, n2 (the
   roll about the tangent is a gauge) and the length factor lambda (element lengths lambda L_h / N), with
   the vertex parameters u_v fixed, alternating with moving every u_v to its local closest point (Newton on
   (C - x) . C' = 0, kept where the distance decreased).  dC/dq from
   :func:`groomtool.rods.clothoid.point_jacobians`, dC/dtheta = -[C - C_0]x (n1, n2) and, because a curve
   of length mu and curvature omega(u) is mu times the unit-length curve of curvature mu omega,
   dC/dlambda = ((C - C_0) + sum_i dC/dq_i q_i) / lambda;
4. the error is the fit's measure (:mod:`groomtool.fit.error`): per strand the max and mean over every input
   vertex of its distance to the local closest point of the curve (Newton from the vertex's parameter);
   strands above tolerance get more elements (factor from the error, error ~ N^-2 assumed, 1.25x - 2x) and
   are fitted again from step 2, until all pass or N reaches ``max_elements``.

A strand stops iterating as soon as every vertex lies within tolerance of its parameter's point (a bound
on its closest-point distance).
"""

from __future__ import annotations

import time
import warnings

import numpy as np
from scipy.spatial.transform import Rotation
from threadpoolctl import threadpool_limits

from ..groom import Groom
from ..rods import clothoid as cl
from ..rods import superhelix as sh
from ..timing import progress as progress_bar
from .fitter import DEFAULT_TOLERANCE_M, FitResult, fit_groom
from .sampling import vertex_arc_lengths

_clock = time.process_time
START_FACTOR = 0.5  # N starts at this fraction of the helix fit's element count
GROWTH_MIN, GROWTH_MAX = 1.25, 2.0
CHUNK_POINTS = 60_000  # vertices x nodes per batch of point Jacobians
WINDOWS = ()  # root-to-tip continuation before the fit on all vertices (_fit_pass); measured worse on harolongo
WARM_START = False  # True: a strand refitted with more elements starts from its best clothoid instead of the helix
#                     fit; measured on 40 harolongo strands: 1,738 elements, 5 strands over tolerance, 19.2 s CPU
#                     against 1,146, 0 and 2.7 s from the helix (the LM stays in the earlier local minimum)
QCAP_TURNS = 2.0  # LM never tries curvatures beyond max(4 |q_start|, this many turns per element)


def project_helix(helix, n_elements: np.ndarray, per_element: int = 32) -> cl.SuperClothoid:
    """The clothoid with ``n_elements`` equal elements over each helix's length whose nodal Darboux values
    are the L2 projection of the helix's piecewise-constant Omega onto the hat functions (root position and
    frame the helix's).  ``helix`` may be a SuperClothoid too (its piecewise-linear Omega projected onto a new
    element count: the warm start of a later pass)."""
    S = helix.n_strands
    n = np.asarray(n_elements, dtype=np.int64)
    N = int(n.max()) if S else 0
    L = helix.strand_lengths
    h = L / np.maximum(n, 1)
    lengths = np.where(np.arange(N)[None, :] < n[:, None], h[:, None], 0.0)
    # midpoints: per strand, n * per_element sub-intervals
    counts = n * per_element
    strand = np.repeat(np.arange(S), counts)
    local = np.arange(len(strand)) - np.repeat(np.cumsum(counts) - counts, counts)
    elem = local // per_element
    frac = ((local % per_element) + 0.5) / per_element
    s = (elem + frac) * h[strand]
    if isinstance(helix, cl.SuperClothoid):
        omega = _omega_at(helix, strand, s)
    else:
        he, _ = sh.locate(helix, strand, s)
        omega = helix.curvatures[strand, he]
    w = (h[strand] / per_element)[:, None]
    b = np.zeros((S, N + 1, 3))
    np.add.at(b, (strand, elem), w * (1.0 - frac)[:, None] * omega)
    np.add.at(b, (strand, elem + 1), w * frac[:, None] * omega)
    rod = cl.SuperClothoid(helix.root_positions, helix.root_frames, lengths, np.zeros((S, N + 1, 3)), n)
    q = cl.stiffness_solve(rod, (1.0, 1.0, 1.0), b)
    return rod.with_curvatures(q)


def _omega_at(rod: cl.SuperClothoid, strand, s):
    """Omega(s) (P, 3), linear between the nodes."""
    elem, t = cl.locate(rod, strand, s)
    l = rod.lengths[strand, elem]
    f = np.where(l > 0, t / np.where(l > 0, l, 1.0), 0.0)[:, None]
    return (1.0 - f) * rod.curvatures[strand, elem] + f * rod.curvatures[strand, elem + 1]


def closest_parameters(rod: cl.SuperClothoid, strand, s, x, iterations: int = 3):
    """Newton on g(s) = (C(s) - x) . C'(s), g' = 1 + (C - x) . C'' (C'' = R (Omega x e0)), from ``s``: the local
    closest points.  Returns (s, distance); a step is kept only where it does not increase the distance."""
    L = rod.strand_lengths[strand]
    kin = cl.kinematics(rod, moments=False)
    pos, R = cl.evaluate(rod, strand, s, kin)
    dist = np.linalg.norm(pos - x, axis=1)
    for _ in range(iterations):
        r = pos - x
        T = R[:, :, 0]
        om = _omega_at(rod, strand, s)
        curv = om[:, 2:3] * R[:, :, 1] - om[:, 1:2] * R[:, :, 2]  # R (Omega x e0)
        g = np.einsum("pk,pk->p", r, T)
        dg = 1.0 + np.einsum("pk,pk->p", r, curv)
        step = np.where(dg > 0.2, g / np.maximum(dg, 0.2), g)
        sn = np.clip(s - step, 0.0, L)
        pn, Rn = cl.evaluate(rod, strand, sn, kin)
        dn = np.linalg.norm(pn - x, axis=1)
        better = dn < dist
        s = np.where(better, sn, s)
        pos = np.where(better[:, None], pn, pos)
        R = np.where(better[:, None, None], Rn, R)
        dist = np.where(better, dn, dist)
    return s, dist


class _Batch:
    """The strands of one LM batch, padded: vertices (B, V, 3), their parameters u (B, V) in [0, 1] (fractions of
    the length), a vertex mask, and the clothoid state (q, root frame, lambda) with a base length L0."""

    def __init__(self, rod: cl.SuperClothoid, L0, X, u, vmask, tol):
        self.rod = rod
        self.L0 = L0
        self.lam = np.ones(rod.n_strands)
        self.X = X
        self.u = u
        self.vmask = vmask
        self.tol = tol
        B, V = vmask.shape
        self.strand = np.repeat(np.arange(B), V)
        self.flat = vmask.ravel()

    def make(self, q, R0, lam):
        n = self.rod.n_elements
        lengths = np.where(np.arange(self.rod.max_elements)[None, :] < n[:, None],
                           (lam * self.L0 / np.maximum(n, 1))[:, None], 0.0)
        return cl.SuperClothoid(self.rod.root_positions, R0, lengths, q, n)

    def sigma(self, lam, u=None):
        return ((lam * self.L0)[:, None] * (self.u if u is None else u)).ravel()

    def residuals_of(self, ids, q, R0, lam):
        """Residuals (len(ids), V, 3) of the strands ``ids`` with curvatures q, root frames R0 and factors lam."""
        n = self.rod.n_elements[ids]
        N = int(n.max())
        lengths = np.where(np.arange(N)[None, :] < n[:, None], (lam * self.L0[ids] / np.maximum(n, 1))[:, None], 0.0)
        rod = cl.SuperClothoid(self.rod.root_positions[ids], R0, lengths, q[:, :N + 1], n)
        V = self.vmask.shape[1]
        strand = np.repeat(np.arange(len(ids)), V)
        sig = ((lam * self.L0[ids])[:, None] * self.u[ids]).ravel()
        r = cl.evaluate_positions(rod, strand, sig).reshape(len(ids), V, 3) - self.X[ids]
        return np.where(self.vmask[ids][..., None], r, 0.0)

    def residuals(self, rod, lam, kin=None):
        pos = cl.evaluate_positions(rod, self.strand, self.sigma(lam), kin)
        r = pos.reshape(self.X.shape) - self.X
        return np.where(self.vmask[..., None], r, 0.0)


def _lm(batch: _Batch, iterations: int, active: np.ndarray):
    """Levenberg-Marquardt iterations on the strands of ``batch`` still ``active`` (bool, updated in place)."""
    rod = batch.rod
    B, V = batch.vmask.shape
    N = rod.max_elements
    nq = 3 * (N + 1)
    n = nq + 3
    mu = np.full(B, 1e-3)
    r = batch.residuals(rod, batch.lam)
    cost = 0.5 * (r ** 2).sum(axis=(1, 2))
    # unknowns of padded nodes: a unit diagonal keeps the normal equations regular (their columns are zero)
    pad_cols = np.zeros((B, n), dtype=bool)
    pad_cols[:, :nq] = ~np.repeat(rod.node_mask, 3, axis=1)
    h = batch.L0 / np.maximum(rod.n_elements, 1)
    qcap = np.maximum(4.0 * np.abs(rod.curvatures).max(axis=(1, 2)), QCAP_TURNS * 2.0 * np.pi / h)
    for _ in range(iterations):
        act = np.flatnonzero(active)
        if not len(act):
            break
        kin = cl.kinematics(rod)
        sig = batch.sigma(batch.lam)
        pts = np.flatnonzero(batch.flat & np.repeat(active, V))
        J = np.zeros((B * V, 3, nq))
        C = np.zeros((B * V, 3))
        step_pts = max(1, CHUNK_POINTS // (N + 1))
        for a in range(0, len(pts), step_pts):
            idx = pts[a:a + step_pts]
            Jp, _ = cl.point_jacobians(rod, batch.strand[idx], sig[idx], kin)
            J[idx] = Jp.transpose(0, 2, 1, 3).reshape(len(idx), 3, nq)
            C[idx] = cl.evaluate_positions(rod, batch.strand[idx], sig[idx], kin)
        J = J.reshape(B, V, 3, nq)
        C = C.reshape(B, V, 3)
        rel = C - rod.root_positions[:, None, :]
        R0 = rod.root_frames
        Jt = -np.einsum("bvij,bjk->bvik", cl.skew(rel), R0[:, :, 1:])
        Jl = (rel + np.einsum("bvij,bj->bvi", J, rod.curvatures.reshape(B, nq))) / batch.lam[:, None, None]
        A = np.concatenate([J, Jt, Jl[..., None]], axis=3)
        A = np.where(batch.vmask[..., None, None], A, 0.0).reshape(B, 3 * V, n)
        At = np.swapaxes(A, 1, 2)
        H = At @ A
        g = (At @ r.reshape(B, 3 * V, 1))[..., 0]
        dH = np.einsum("bii->bi", H).copy()
        empty = pad_cols | (dH <= 0.0)
        dH = np.where(empty, 1.0, dH)
        improved = np.zeros(B, dtype=bool)
        for _ in range(8):
            trial = np.flatnonzero(active & ~improved)
            if not len(trial):
                break
            M = H[trial] + (mu[trial, None] * dH[trial] + 1e-30 + empty[trial])[:, :, None] * np.eye(n)
            step = np.linalg.solve(M, -g[trial][..., None])[..., 0]
            q = rod.curvatures[trial] + step[:, :nq].reshape(len(trial), N + 1, 3) * rod.node_mask[trial][..., None]
            rot = np.einsum("bij,bj->bi", R0[trial][:, :, 1:], step[:, nq:nq + 2])
            R0n = Rotation.from_rotvec(rot).as_matrix() @ R0[trial]
            lamn = np.maximum(batch.lam[trial] + step[:, -1], 0.5 * batch.lam[trial])
            # a step to curvatures beyond the cap is refused without evaluating it (the series' sub-step count
            # grows with the curvature: a wild trial step would cost minutes)
            wild = np.abs(q).max(axis=(1, 2)) > qcap[trial]
            q[wild] = rod.curvatures[trial][wild]
            rn = batch.residuals_of(trial, q, R0n, lamn)
            cn = 0.5 * (rn ** 2).sum(axis=(1, 2))
            ok_t = (cn < cost[trial]) & ~wild
            mu[trial] = np.where(ok_t, np.maximum(mu[trial] / 3.0, 1e-12), mu[trial] * 4.0)
            if ok_t.any():
                ids = trial[ok_t]
                qk = rod.curvatures.copy()
                qk[ids] = q[ok_t]
                Rk = rod.root_frames.copy()
                Rk[ids] = R0n[ok_t]
                lk = batch.lam.copy()
                lk[ids] = lamn[ok_t]
                rel_gain = (cost[ids] - cn[ok_t]) / np.maximum(cost[ids], 1e-300)
                rod = batch.make(qk, Rk, lk)
                batch.rod = rod
                batch.lam = lk
                r[ids] = rn[ok_t]
                cost[ids] = cn[ok_t]
                improved[ids] = True
                # converged in the least-squares sense: no more iterations for it
                active[ids[rel_gain < 1e-10]] = False
        active &= improved  # a strand no step improves is done
        # every vertex within tolerance of its parameter's point: done
        worst = np.sqrt((r ** 2).sum(axis=2)).max(axis=1)
        active &= ~(worst <= batch.tol)
    batch.rod = rod
    return rod


def _fit_pass(rod0: cl.SuperClothoid, L0, X, u, vmask, tol, iterations: int, rounds: int,
              windows=WINDOWS):
    """LM on one padded batch: first on growing windows of the vertices from the root (``windows``: fractions
    of the length; the curvature beyond a window does not move the points inside it, so each window starts
    from a fitted root part instead of an error accumulated along the strand), then ``rounds`` times on all
    vertices followed by closest-point updates of their parameters.  Returns (rod, u, distances)."""
    B, V = vmask.shape
    batch = _Batch(rod0, L0, X, u, vmask, tol)
    for w in windows:
        batch.vmask = vmask & (u <= w)
        batch.flat = batch.vmask.ravel()
        _lm(batch, iterations, np.ones(B, dtype=bool))
    batch.vmask = vmask
    batch.flat = vmask.ravel()
    sel = batch.flat
    for rnd in range(rounds):
        r = batch.residuals(batch.rod, batch.lam)
        active = ~(np.sqrt((r ** 2).sum(axis=2)).max(axis=1) <= tol)
        if not active.any():
            break
        _lm(batch, iterations, active)
        s0 = batch.sigma(batch.lam)
        s_new, _ = closest_parameters(batch.rod, batch.strand[sel], s0[sel], X.reshape(-1, 3)[sel])
        u_new = batch.u.copy().ravel()
        u_new[sel] = s_new / (batch.lam * L0)[batch.strand[sel]]
        batch.u = u_new.reshape(B, V)
    s0 = batch.sigma(batch.lam)
    s_new, dist = closest_parameters(batch.rod, batch.strand[sel], s0[sel], X.reshape(-1, 3)[sel])
    d = np.zeros(B * V)
    d[sel] = dist
    u_new = batch.u.copy().ravel()
    u_new[sel] = s_new / (batch.lam * L0)[batch.strand[sel]]
    return batch.rod, u_new.reshape(B, V), d.reshape(B, V)


def fit_clothoid_groom(groom: Groom, tolerance: float | None = DEFAULT_TOLERANCE_M,
                       relative_tolerance: float | None = None, max_elements: int = 256, iterations: int = 6,
                       rounds: int = 3, helix_fit: FitResult | None = None, batch_strands: int = 256,
                       progress: bool = False) -> FitResult:
    """Fit every strand of ``groom`` with a Super Space Clothoid within tolerance, N chosen per strand (module
    docstring).  Returns a :class:`~groomtool.fit.fitter.FitResult` whose ``helix`` is the
    :class:`~groomtool.rods.clothoid.SuperClothoid` (``settings["model"] == "clothoid"``); ``helix_fit``: the
    Super-Helix fit to start from (default: :func:`fit_groom` with the same tolerances).  Strands still above
    tolerance at ``max_elements`` are reported (converged False, a warning), never dropped."""
    t_start = _clock()
    timings = {}
    if helix_fit is None:
        helix_fit = fit_groom(groom, tolerance=tolerance, relative_tolerance=relative_tolerance,
                              max_elements=max_elements)
    timings["helix_fit"] = _clock() - t_start
    helix = helix_fit.helix
    tol = np.asarray(helix_fit.tolerance, dtype=np.float64)
    S = helix.n_strands
    offsets = groom.offsets
    counts = np.diff(offsets)
    varc, vlen = vertex_arc_lengths(groom.points, groom.offsets)
    vfrac = varc / np.maximum(vlen[groom.strand_index], 1e-300)
    n_now = np.clip(np.ceil(START_FACTOR * helix.n_elements).astype(np.int64), 2, max_elements)
    max_err, mean_err = np.full(S, np.inf), np.full(S, np.inf)
    best = {}
    prev_n, prev_err = np.zeros(S, dtype=np.int64), np.zeros(S)
    active = np.arange(S)
    passes = 0
    bar = None
    if progress:
        bar = progress_bar(S, "fit (clothoid)", quiet=False, unit="strand")
    while len(active):
        passes += 1
        order = active[np.lexsort((counts[active], n_now[active]))]
        errs = np.empty(len(order))
        for a in range(0, len(order), batch_strands):
            ids = order[a:a + batch_strands]
            # first pass: from the helix fit; later passes (WARM_START): from the strand's best clothoid so far
            sub = _merge([best[s][0] for s in ids]) if (WARM_START and passes > 1) else helix.subset(ids)
            rod0 = project_helix(sub, n_now[ids])
            V = int(counts[ids].max())
            local = np.arange(V)[None, :]
            vmask = local < counts[ids, None]
            vidx = np.where(vmask, offsets[ids, None] + local, 0)
            X = np.where(vmask[..., None], groom.points[vidx], 0.0)
            u = np.where(vmask, vfrac[vidx], 0.0)
            with threadpool_limits(1, user_api="blas"):  # small batched solves: threads only cost
                rod, u, d = _fit_pass(rod0, sub.strand_lengths, X, u, vmask, tol[ids], iterations, rounds)
            mx = d.max(axis=1)
            mn = d.sum(axis=1) / counts[ids]
            for i, s in enumerate(ids):
                if mx[i] < max_err[s]:  # keep the best fit seen (a larger N is not always better for a local fit)
                    best[s] = (rod.subset([i]), mx[i], mn[i])
                    max_err[s], mean_err[s] = mx[i], mn[i]
            errs[a:a + len(ids)] = mx
        done = (max_err[order] <= tol[order]) | (n_now[order] >= max_elements)
        if bar is not None:
            bar.update(int(done.sum()))
        nd = order[~done]
        e = errs[~done]
        grow = np.clip(1.1 * (e / tol[nd]) ** 0.5, GROWTH_MIN, GROWTH_MAX)
        prev_n[nd], prev_err[nd] = n_now[nd], e
        n_now[nd] = np.minimum(np.ceil(n_now[nd] * grow).astype(np.int64), max_elements)
        active = nd
    if bar is not None:
        bar.close()
    rod = _merge([best[s][0] for s in range(S)])
    converged = max_err <= tol
    if not converged.all():
        bad = np.flatnonzero(~converged)
        warnings.warn(f"{groom.source}: {len(bad)} strand(s) above tolerance with the clothoid fit at "
                      f"max_elements={max_elements} (worst {max_err[bad].max():.3g} m, strand "
                      f"{bad[np.argmax(max_err[bad])]})", stacklevel=2)
    timings["total"] = _clock() - t_start
    timings["clothoid"] = timings["total"] - timings["helix_fit"]
    settings = {"model": "clothoid", "tolerance": tolerance, "relative_tolerance": relative_tolerance,
                "max_elements": max_elements, "iterations": iterations, "rounds": rounds,
                "start_factor": START_FACTOR, "helix_elements": int(helix.n_elements.sum())}
    return FitResult(rod, max_err, mean_err, converged, tol, helix_fit.strand_lengths, passes, timings, settings)


def _merge(rods) -> cl.SuperClothoid:
    """One padded SuperClothoid from one-strand clothoids."""
    S = len(rods)
    N = max((int(r.n_elements[0]) for r in rods), default=0)
    roots, frames = np.zeros((S, 3)), np.zeros((S, 3, 3))
    lengths, q = np.zeros((S, N)), np.zeros((S, N + 1, 3))
    n = np.zeros(S, dtype=np.int64)
    for i, r in enumerate(rods):
        k = int(r.n_elements[0])
        roots[i], frames[i], n[i] = r.root_positions[0], r.root_frames[0], k
        lengths[i, :k] = r.lengths[0, :k]
        q[i, :k + 1] = r.curvatures[0, :k + 1]
    return cl.SuperClothoid(roots, frames, lengths, q, n)
