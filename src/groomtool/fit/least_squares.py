"""The least-squares fitting prototype of docs/clothoid.md: one polyline fitted by N equal elements of a
Super Space Clothoid or of a Super-Helix by the same procedure (:func:`fit_polyline_ls`), and the
smallest N reaching a tolerance (:func:`min_elements_ls`); bench/bench_models.py compares the two
models with it.  Production fitting is :mod:`groomtool.fit.fitter` (floating tangents).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..rods import clothoid as cl
from ..rods import superhelix as sh
from .fitter import fit_polyline_fixed


def polyline_distances(points: np.ndarray, curve: np.ndarray) -> np.ndarray:
    """Distance from each point (V, 3) to the polyline ``curve`` (M, 3) (nearest segment, brute force)."""
    a = curve[:-1]
    d = curve[1:] - a
    dd = np.maximum(np.einsum("mk,mk->m", d, d), 1e-300)
    out = np.empty(len(points))
    for i, x in enumerate(points):
        t = np.clip(np.einsum("mk,mk->m", x - a, d) / dd, 0.0, 1.0)
        out[i] = np.sqrt(((a + t[:, None] * d - x) ** 2).sum(axis=1).min())
    return out


@dataclass
class LeastSquaresFit:
    """Result of :func:`fit_polyline_ls`: the rod (a one-strand SuperClothoid or SuperHelix), the max and mean
    distance from the vertices to the fitted curve (m), the iterations run and the final residual norm."""

    rod: object
    max_error: float
    mean_error: float
    iterations: int
    residual: float


def fit_polyline_ls(polyline, n_elements: int, model: str = "clothoid", iterations: int = 40, rounds: int = 3,
                    samples_per_element: int = 32) -> LeastSquaresFit:
    """Prototype fit of one polyline (V, 3) by ``n_elements`` equal elements of a Super Space Clothoid
    (``model="clothoid"``: G2, nodal Omega) or of a Super-Helix (``model="helix"``), the same way for both:

    start from floating-tangent helix fits with N and up to 4N elements (:func:`groomtool.fit.fit_polyline_fixed`),
    their Darboux vectors projected in L2 onto the model's space (element means / nodal hat functions), the one
    with the lower cost (with its root frame), then ``rounds`` times:
    Levenberg-Marquardt (``iterations`` in all) on sum_v |C(lambda L u_v) - x_v|^2 with the vertex parameters
    u_v fixed (first round: polyline arc length / L), over q, a rotation theta of the root frame about its
    normals n1, n2 (a roll about the tangent is a gauge: it only rotates (kappa1, kappa2)) and the length
    factor lambda (element lengths lambda L / N, the root fixed at x_0; dC/dq from ``point_jacobians``,
    dC/dtheta = -[C - C_0]x (n1, n2), dC/dlambda by central differences), then each u_v moved
    to its closest point (Newton on (C - x).T = 0, kept only where the distance decreased).  Every step
    lowers the cost.  The error is the distance from every vertex to the fitted curve sampled at
    ``samples_per_element`` points per element (nearest segment).
    """
    X = np.asarray(polyline, dtype=np.float64)
    s_poly = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(X, axis=0), axis=1))])
    L = s_poly[-1]
    N = int(n_elements)
    # initial guesses: floating-tangent helix fits with N and with up to 4N elements, their Darboux vectors
    # projected (L2, on a dense grid) onto the model's space (piecewise constant / continuous piecewise
    # linear on N equal elements); the one with the lower starting cost is refined
    if model == "clothoid":
        mod = cl
        make = lambda q, R, lam: cl.SuperClothoid(X[0], R, np.full((1, N), lam * L / N), q[None])
    elif model == "helix":
        mod = sh
        make = lambda q, R, lam: sh.SuperHelix(X[0], R, np.full((1, N), lam * L / N), q[None])
    else:
        raise ValueError(f"model must be 'clothoid' or 'helix', got {model!r}")
    V = len(X)
    strand = np.zeros(V - 1, dtype=np.int64)
    u = s_poly[1:] / L
    best = None
    for n_fine in sorted({N, int(max(N, min(4 * N, (V - 1) // 2)))}):
        init = fit_polyline_fixed(X, arc_lengths=np.linspace(0.0, L, n_fine + 1)).helix
        grid = (np.arange(64 * n_fine) + 0.5) / (64 * n_fine)  # fractions of the length
        omega = init.curvatures[0][np.minimum((grid * n_fine).astype(np.int64), n_fine - 1)]
        x = grid * N
        e = np.minimum(x.astype(np.int64), N - 1)
        if model == "clothoid":
            basis = np.zeros((len(grid), N + 1))
            basis[np.arange(len(grid)), e] = 1.0 - (x - e)
            basis[np.arange(len(grid)), e + 1] = x - e
            q0 = np.linalg.lstsq(basis, omega, rcond=None)[0]
        else:
            q0 = np.stack([omega[e == j].mean(axis=0) for j in range(N)])
        lam0 = init.strand_lengths[0] / L
        r0 = mod.evaluate_positions(make(q0, init.root_frames[0], lam0), strand, lam0 * L * u) - X[1:]
        c0 = 0.5 * (r0 ** 2).sum()
        if best is None or c0 < best[0]:
            best = (c0, q0, init.root_frames[0].copy(), lam0)
    _, q, R0, lam = best
    nq = q.size
    rod = make(q, R0, lam)
    r = mod.evaluate_positions(rod, strand, lam * L * u) - X[1:]
    cost = 0.5 * (r ** 2).sum()
    mu = 1e-3
    it = 0
    per_round = max(1, iterations // max(rounds, 1))
    for rnd in range(rounds):
        for _ in range(per_round):
            it += 1
            sig = lam * L * u
            J, _ = mod.point_jacobians(rod, strand, sig)
            Jq = J.transpose(0, 2, 1, 3).reshape(V - 1, 3, nq)
            Jt = -cl.skew(r + X[1:] - X[0]) @ R0[:, 1:]  # root turns about n1, n2 (the roll about n0 is a gauge)
            eps = 1e-7
            Jl = ((mod.evaluate_positions(make(q, R0, lam + eps), strand, (lam + eps) * L * u)
                   - mod.evaluate_positions(make(q, R0, lam - eps), strand, (lam - eps) * L * u)) / (2 * eps))
            A = np.concatenate([Jq, Jt, Jl[..., None]], axis=2).reshape(3 * (V - 1), -1)
            g = A.T @ r.ravel()
            H = A.T @ A
            improved = False
            for _ in range(12):
                step = np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-300) + 1e-30 * np.eye(len(g)), -g)
                qn = q + step[:nq].reshape(q.shape)
                Rn = Rotation.from_rotvec(R0[:, 1:] @ step[nq:nq + 2]).as_matrix() @ R0
                ln = lam + step[-1]
                rodn = make(qn, Rn, ln)
                rn = mod.evaluate_positions(rodn, strand, ln * L * u) - X[1:]
                cn = 0.5 * (rn ** 2).sum()
                if cn < cost:
                    improved = True
                    break
                mu *= 4.0
            if not improved:
                break
            rel = (cost - cn) / max(cost, 1e-300)
            q, R0, lam, r, rod, cost = qn, Rn, ln, rn, rodn, cn
            mu = max(mu / 3.0, 1e-12)
            if rel < 1e-8:
                break
        if rnd == rounds - 1:
            break
        # closest points: Newton on (C(sigma) - x) . T(sigma) = 0, keep where the distance went down
        un = u.copy()
        for _ in range(4):
            pos, fr = mod.evaluate(rod, strand, lam * L * un)
            un = np.clip(un - np.einsum("pk,pk->p", pos - X[1:], fr[:, :, 0]) / (lam * L), 0.0, 1.0)
        rn = mod.evaluate_positions(rod, strand, lam * L * un) - X[1:]
        better = (rn ** 2).sum(axis=1) < (r ** 2).sum(axis=1)
        u = np.where(better, un, u)
        r = np.where(better[:, None], rn, r)
        cost = 0.5 * (r ** 2).sum()
        mu = 1e-3
    pts = mod.sample(rod, samples_per_element)[0]
    d = polyline_distances(X, pts)
    return LeastSquaresFit(rod, float(d.max()), float(d.mean()), it, float(np.sqrt(2 * cost)))


def min_elements_ls(polyline, tolerance: float, model: str = "clothoid", n_max: int = 256, start: int | None = None):
    """Smallest N (searched: doubling, then bisection) whose :func:`fit_polyline_ls` has max error <= tolerance.

    Returns (N, fit at N, number of fits run); (None, best fit, fits) when n_max does not reach it.
    """
    X = np.asarray(polyline, dtype=np.float64)
    L = np.linalg.norm(np.diff(X, axis=0), axis=1).sum()
    fits = {}

    def ok(n):
        if n not in fits:
            fits[n] = fit_polyline_ls(X, n, model)
        return fits[n].max_error <= tolerance

    n = max(1, int(start if start is not None else np.ceil(L / 0.02)))
    if ok(n):
        hi = n
        lo = 0
        while hi > 1:
            m = max(1, hi // 2)
            if ok(m):
                hi = m
            else:
                lo = m
                break
    else:
        lo = n
        hi = None
        while lo < n_max:
            m = min(2 * lo, n_max)
            if ok(m):
                hi = m
                break
            lo = m
        if hi is None:
            best = min(fits.values(), key=lambda f: f.max_error)
            return None, best, len(fits)
    while hi - lo > 1:
        m = (lo + hi) // 2
        if ok(m):
            hi = m
        else:
            lo = m
    return hi, fits[hi], len(fits)

