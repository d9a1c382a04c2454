"""Anderson acceleration (type II, Walker & Ni 2011) of a fixed-point map x -> G(x), used on the
Gauss-Seidel sweep.

With f_k = G(x_k) - x_k and the last p differences dX = [x_{i+1} - x_i], dF = [f_{i+1} - f_i]:

    gamma   = argmin ||f_k - dF gamma||      (normal equations, Tikhonov-regularised)
    x_{k+1} = x_k + f_k - (dX + dF) gamma

The differences live in ring buffers and the Gram matrix dF^T dF is updated one row at a time, so one
step costs about 6 p n flops (vectorised reductions: fastmath reassociates the dot products, still
deterministic).  Numba kernels, single-threaded,
deterministic.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

RESTART_GROWTH = 10.0  #: guarded_step restarts the history when ||f|| grows this much over its smallest since


@njit(cache=True, fastmath=True)
def _dot(a, b):
    """sum a_k b_k accumulated in float64 (a, b may be float32)."""
    s = 0.0
    for k in range(a.shape[0]):
        s += np.float64(a[k]) * np.float64(b[k])
    return s


def norm(x: np.ndarray) -> float:
    """||x|| of a float64 vector in this thread (np.linalg.norm goes through OpenBLAS, whose threads then
    spin between the solver's calls: 2x the CPU time for nothing on a 2-core machine, issue 22)."""
    return math.sqrt(_dot(x, x))


@njit(cache=True, fastmath=True)
def _push_and_project(x, f, x_prev, f_prev, dS, dF, gram, rhs, slot, count, store):
    """If store: dF[slot] = f - f_prev, dS[slot] = (x - x_prev) + dF[slot] and row `slot` of
    gram = dF dF^T is refreshed.  Always rhs = dF f; then x_prev, f_prev <- x, f.
    (dS = dX + dF is what the mixing needs.)"""
    n = x.shape[0]
    if store:
        for k in range(n):
            df = f[k] - f_prev[k]
            dF[slot, k] = df
            dS[slot, k] = (x[k] - x_prev[k]) + df
        for j in range(count):
            g = _dot(dF[slot], dF[j])
            gram[slot, j] = g
            gram[j, slot] = g
    for j in range(count):
        rhs[j] = _dot(dF[j], f)
    for k in range(n):
        x_prev[k] = x[k]
        f_prev[k] = f[k]


@njit(cache=True, fastmath=True)
def _mix(x, f, dS, gram, rhs, count, reg, out):
    """out = x + f - dS^T gamma,  (gram + reg tr(gram)/p I) gamma = rhs."""
    n = x.shape[0]
    G = gram[:count, :count].copy()
    tr = 0.0
    for j in range(count):
        tr += G[j, j]
    lam = reg * tr / max(count, 1) + 1e-300
    for j in range(count):
        G[j, j] += lam
    gamma = np.linalg.solve(G, rhs[:count].copy())
    for k in range(n):
        out[k] = x[k] + f[k]
    for j in range(count):
        gj = gamma[j]
        row = dS[j]
        for k in range(n):
            out[k] -= gj * np.float64(row[k])


class AndersonMixer:
    """Ring-buffer Anderson mixing for vectors of length n with memory p."""

    def __init__(self, n: int, memory: int = 5, reg: float = 1e-10, dtype=np.float32):
        """dtype: storage of the history.  float32 halves its memory traffic; it only perturbs the mixing
        direction (the iterates that are returned and measured are always float64 sweep outputs)."""
        self.memory = int(memory)
        self.reg = float(reg)
        self.dS = np.zeros((self.memory, n), dtype=dtype)  # dX + dF
        self.dF = np.zeros((self.memory, n), dtype=dtype)
        self.gram = np.zeros((self.memory, self.memory))
        self.rhs = np.zeros(self.memory)
        self.x_prev = np.zeros(n)
        self.f_prev = np.zeros(n)
        self.count = 0
        self.slot = 0
        self.has_prev = False
        self.best = math.inf  # the smallest ||f|| since the last reset (guarded_step)

    @property
    def nbytes(self) -> int:
        return self.dS.nbytes + self.dF.nbytes + self.x_prev.nbytes + self.f_prev.nbytes

    def reset(self) -> None:
        self.count = 0
        self.slot = 0
        self.has_prev = False
        self.best = math.inf

    def guarded_step(self, x: np.ndarray, f: np.ndarray, out: np.ndarray) -> bool:
        """:meth:`step`, after restarting the history when ||f|| grew RESTART_GROWTH-fold over the smallest since
        the last reset (the mixing diverges: seen with Gauss-Seidel and ADMM on hair problems).  Returns whether
        it restarted."""
        fn = norm(f)  # not np.linalg.norm: no BLAS threads (issue 22)
        restarted = fn > RESTART_GROWTH * self.best
        if restarted:
            self.reset()
        self.best = min(self.best, fn)
        self.step(x, f, out)
        return restarted

    def step(self, x: np.ndarray, f: np.ndarray, out: np.ndarray) -> None:
        """out = the next iterate from x_k, f_k = G(x_k) - x_k (plain x + f until there is history)."""
        store = self.has_prev
        slot = self.slot
        count = min(self.count + 1, self.memory) if store else self.count
        _push_and_project(x, f, self.x_prev, self.f_prev, self.dS, self.dF, self.gram, self.rhs, slot, count, store)
        if store:
            self.count = count
            self.slot = (slot + 1) % self.memory
        self.has_prev = True
        if self.count == 0:
            np.add(x, f, out=out)
        else:
            _mix(x, f, self.dS, self.gram, self.rhs, self.count, self.reg, out)
