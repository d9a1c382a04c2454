"""Accelerated projected gradient (APGD, Mazhar et al. 2015) for the SOCQP

    min 1/2 r^T W r + b^T r,   r_i in K_mu_i.

Nesterov's method with adaptive restart (O'Donoghue & Candes 2015), preconditioned by the per-contact
scalar rho_i = 3 / trace(W_ii) (the cones are invariant under a positive scaling of each block, so the
projection in that metric is still the plain cone projection):

    x_{k+1}     = P_K( y_k - t P (W y_k + b) ),      P = diag(rho_i I_3),  t = 1 / lambda_max(P^1/2 W P^1/2)
    theta_{k+1} = (-theta_k^2 + theta_k sqrt(theta_k^2 + 4)) / 2,   beta = theta_k (1 - theta_k) / (theta_k^2 + theta_{k+1})
    y_{k+1}     = x_{k+1} + beta (x_{k+1} - x_k)
    restart (y_{k+1} = x_{k+1}, theta = 1) when (W y_k + b) . (x_{k+1} - x_k) > 0

One product with W per iteration: W y is carried along as W x_{k+1} + beta (W x_{k+1} - W x_k).
lambda_max comes from a power iteration (+5 %).  Stops on the residual of residual.py.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from . import residual as _res
from .blocks import upper_block_matvec
from .cones import SOC, project_cone
from .gauss_seidel import packed_apply, packed_transpose_apply

_FM = {"contract"}


@njit(cache=True, fastmath=_FM)
def _gradient_step(y, wy, b, rho, mu, t, x_new):
    """x_new_i = P_K(y_i - t rho_i (wy_i + b_i)); returns sum_i (wy_i + b_i) . (x_new_i - y_i) (unused)."""
    for i in range(y.shape[0]):
        s = t * rho[i]
        z0 = y[i, 0] - s * (wy[i, 0] + b[i, 0])
        z1 = y[i, 1] - s * (wy[i, 1] + b[i, 1])
        z2 = y[i, 2] - s * (wy[i, 2] + b[i, 2])
        p0, p1, p2 = project_cone(mu[i], z0, z1, z2)
        x_new[i, 0] = p0
        x_new[i, 1] = p1
        x_new[i, 2] = p2


@njit(cache=True, fastmath=_FM)
def _restart_test(wy, b, x_new, x):
    """(W y + b) . (x_new - x)."""
    s = 0.0
    for i in range(x.shape[0]):
        for a in range(3):
            s += (wy[i, a] + b[i, a]) * (x_new[i, a] - x[i, a])
    return s


@njit(cache=True, fastmath=_FM)
def _extrapolate(x_new, x, wx_new, wx, beta, y, wy):
    """y = x_new + beta (x_new - x), wy = wx_new + beta (wx_new - wx); then x <- x_new, wx <- wx_new."""
    for i in range(x.shape[0]):
        for a in range(3):
            y[i, a] = x_new[i, a] + beta * (x_new[i, a] - x[i, a])
            wy[i, a] = wx_new[i, a] + beta * (wx_new[i, a] - wx[i, a])
            x[i, a] = x_new[i, a]
            wx[i, a] = wx_new[i, a]


class UpperMatvec:
    """x -> W x with W as an upper 3x3-block triangle (blocks.UpperBlockDelassus)."""

    def __init__(self, W):
        self.W = W
        m = W.n_contacts
        self.zero = np.zeros((m, 3))

    def __call__(self, x, out):
        upper_block_matvec(self.W.indptr, self.W.indices, self.W.blocks, x, self.zero, out)


class FactoredMatvec:
    """x -> W x = H (D (H^T x)) + 2 gamma x from the packed H and H D of a ContactProblem."""

    def __init__(self, problem):
        self.H, self.G = problem.packed()
        self.n = problem.n_dofs
        self.gamma2 = 2.0 * problem.gamma
        self.v = np.zeros(self.n)
        self.zero = np.zeros((problem.n_contacts, 3))

    def __call__(self, x, out):
        packed_transpose_apply(self.G.ptr, self.G.cols, self.G.vals, x, self.n, self.v)
        packed_apply(self.H.ptr, self.H.cols, self.H.vals, self.v, self.gamma2, x, self.zero, out)


def lambda_max(matvec, rho: np.ndarray, m: int, iters: int = 30, seed: int = 0) -> float:
    """Largest eigenvalue of P^1/2 W P^1/2 by power iteration (P = diag(rho_i I_3))."""
    rng = np.random.default_rng(seed)
    sq = np.sqrt(rho)[:, None]
    v = rng.normal(size=(m, 3))
    v /= np.linalg.norm(v)
    w = np.empty_like(v)
    lam = 0.0
    for _ in range(iters):
        matvec(sq * v, w)
        w *= sq
        lam_new = float(np.sum(v * w))
        nw = np.linalg.norm(w)
        if nw == 0:
            return 0.0
        v = w / nw
        if abs(lam_new - lam) <= 1e-3 * abs(lam_new):
            lam = lam_new
            break
        lam = lam_new
    return lam


@dataclass
class APGDOutcome:
    r: np.ndarray
    residual: float
    iterations: int
    converged: bool
    restarts: int
    history: list = field(default_factory=list)
    solve_s: float = 0.0
    stopped_by_rule: bool = False  # the caller's ``stop`` accepted r (before the residual reached tol)


def run_apgd(
    matvec,
    b: np.ndarray,
    mu: np.ndarray,
    rho: np.ndarray,
    *,
    tol: float = 1e-8,
    max_iter: int = 10000,
    r0: np.ndarray | None = None,
    check_every: int = 10,
    scale: float | None = None,
    time_limit: float | None = None,
    callback=None,
    stop=None,
) -> APGDOutcome:
    """APGD (module docstring) on u = W r + b given x -> W x (matvec(x, out), x/out (m, 3)).
    callback(iterations, residual) at every residual check; stop(r, u) -> bool, asked at every check with the
    current x (in the cones) and u = W x + b (both (3m,)): True ends the run (outcome.stopped_by_rule), as in
    gauss_seidel.run_gauss_seidel."""
    t0 = time.perf_counter()
    m = b.size // 3
    b = np.ascontiguousarray(np.asarray(b, dtype=np.float64).reshape(m, 3))
    mu = np.ascontiguousarray(mu, dtype=np.float64)
    rho = np.ascontiguousarray(rho, dtype=np.float64)
    if scale is None:
        scale = _res.residual_scale(b, rho)
    lam = lambda_max(matvec, rho, m)
    t = 1.0 / (1.05 * lam) if lam > 0 else 1.0
    x = np.zeros((m, 3)) if r0 is None else np.array(np.asarray(r0, dtype=np.float64).reshape(m, 3), order="C")
    # start from a feasible point
    zero = np.zeros((m, 3))
    _gradient_step(x.copy(), zero, zero, rho, mu, 0.0, x)
    wx = np.empty_like(x)
    matvec(x, wx)
    y = x.copy()
    wy = wx.copy()
    x_new = np.empty_like(x)
    wx_new = np.empty_like(x)
    theta = 1.0
    restarts = 0
    emax, _ = _res.residual_max_rms(SOC, x, wx + b, mu, rho)
    res = emax / scale
    history = [(0, res, time.perf_counter() - t0)]
    k = 0
    by_rule = False
    while res > tol and k < max_iter:
        _gradient_step(y, wy, b, rho, mu, t, x_new)
        matvec(x_new, wx_new)
        k += 1
        if _restart_test(wy, b, x_new, x) > 0.0:
            theta_new, beta = 1.0, 0.0
            restarts += 1
        else:
            theta_new = 0.5 * (-theta * theta + theta * math.sqrt(theta * theta + 4.0))
            beta = theta * (1.0 - theta) / (theta * theta + theta_new)
        _extrapolate(x_new, x, wx_new, wx, beta, y, wy)
        theta = theta_new
        if k % check_every == 0 or k == max_iter:
            # wx now holds W x_{k}
            emax, _ = _res.residual_max_rms(SOC, x, wx + b, mu, rho)
            res = emax / scale
            history.append((k, res, time.perf_counter() - t0))
            if callback is not None:
                callback(k, res)
            if res > tol and stop is not None and stop(x.reshape(-1).copy(), (wx + b).reshape(-1)):
                by_rule = True
                break
            if time_limit is not None and time.perf_counter() - t0 > time_limit:
                break
            if not math.isfinite(res):
                break
    return APGDOutcome(x.reshape(-1).copy(), float(res), k, bool(res <= tol), restarts, history, time.perf_counter() - t0,
                       by_rule)
