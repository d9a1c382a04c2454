"""Super Space Clothoids (Casati and Bertails-Descoubes, SIGGRAPH 2013; docs/maths.md section 3), batched.

A strand is N elements of lengths l_j.  The material Darboux vector Omega(s) = (twist, kappa1, kappa2) is
**continuous and piecewise linear**: the generalised coordinates are its values q_i at the N + 1 nodes,

    Omega(S_j + t) = a_j + b_j t,   a_j = q_j,  b_j = (q_{j+1} - q_j) / l_j,   t in [0, l_j].

(Continuity makes the curvature C0 and the centreline C2; per-element start values and slopes would
give 6N unknowns and a discontinuous curvature, i.e. a C1 centreline like the Super-Helix.)  Frames
are 3x3 matrices whose **columns** are (n0, n1, n2), n0 the tangent, as in :mod:`.superhelix`:

    R' = R [Omega]x,   C' = R e0.

On an element R(S_j + t) = R_j Phi(t), C = C_j + R_j p(t), with Phi' = Phi [a + b t]x, p' = Phi e0.
There is no closed form: the element is cut into m equal sub-steps of length h with

    2 (|a|_max h + |b| h^2) <= RHO = 1            (|a|_max = max(|a_j|, |a_j + b_j l_j|)),

and on each sub-step (start tau0, a' = a + b tau0) the propagator Psi(u) = Phi(tau0)^T Phi(tau0 + u) is
the power series Psi = sum_k Psi_k u^k of Psi' = Psi ([a']x + u [b]x):

    Psi_0 = I,  (k + 1) Psi_{k+1} = Psi_k [a']x + Psi_{k-1} [b]x.

Truncation (rigorous): ||Psi_k|| h^k <= d_k, the coefficients of exp(alpha x + beta x^2 / 2) at x = 1
with alpha = |a'| h, beta = |b| h^2 (same recurrence on norms).  The auxiliary series below are
Cauchy products bounded by the coefficients d_k of exp(2 alpha x + beta x^2), and for k >= K the tail
sum_{k > K} d_k <= 2 r max(d_K, d_{K-1}) / (1 - r), r = (2 alpha + 2 beta) / (K + 1).  K is the
first index where this bound is below TOL = 1e-16 (relative to |Psi| = 1, |xi| <= h, |zeta| <= h^2);
the series are summed to K + 2 for the values (xi and zeta lag Psi by one and two orders) and to K + 4 so
that their first derivatives in (a, b) are covered too (d d_k / d alpha = 2 d_{k-1}, d d_k / d beta = 2 d_{k-2}
with respect to the scaled rates: the complex step below differentiates the truncated sums).  With RHO = 1,
K is about 18.

Besides Phi, p and P = int p, every derivative needs weighted integrals of the states

    X = [p]x Phi,   Z = [P]x Phi,      X' = Phi [e0]x + X [Omega]x,   Z' = X + Z [Omega]x,

which obey a linear ODE with the same structure, so their sub-step propagators xi = [pi]x Psi,
zeta = [Pi]x Psi are power series too:

    (k + 1) xi_{k+1}   = Psi_k [e0]x + xi_k [a']x + xi_{k-1} [b]x,
    (k + 1) zeta_{k+1} = xi_k        + zeta_k [a']x + zeta_{k-1} [b]x,

and their moments int_0^h u^i Y(u) du = sum_k Y_k h^(k+i+1) / (k + i + 1) are exact term by term.

Derivatives.  A change dOmega(s) turns the frame at s by the world rotation vector
psi(s) = int_0^s R dOmega, so dC(s) = -int_0^s [C(s) - C(tau)]x R(tau) dOmega(tau) dtau, and with the hat
functions N_i of the nodes,

    dC(s)/dq_i = -int_0^s N_i(tau) [C(s) - C(tau)]x R(tau) dtau
               = sum_k ([C_k - C(s)]x R_k int N_i Phi + R_k int N_i X)       (over elements k, up to s).

Gravity V = -rhoS g . int C ds; F_i = -dV/dq_i = rhoS int N_i(tau) R(tau)^T (Y(tau) x g) dtau with
Y(tau) = int_tau^L (C(s) - C(tau)) ds (the gravity torque of the part beyond tau, in the material frame);
on element k, R_k^T Y = y0 - P(t) - (m + l - t) p(t) (m = L - S_{k+1}), so the integrand is
-([y0]x Phi - Z - (m + l) X + t X)^T R_k^T g, whose moments are the series above.  dF/dq is obtained by
the complex step (F evaluated at q + i eps e_j, eps = 1e-30: exact to round-off, no cancellation); every
kernel is dtype-generic for that.  Step sizes and term counts use real parts only.

Elastic energy (Omega and Omega0 both linear per element, d = q - q0 at the nodes):

    E = 1/2 int (Omega - Omega0)^T D (Omega - Omega0) ds = 1/2 sum_j l_j/3 (d_j^2 + d_j d_{j+1} + d_{j+1}^2) D,

so K = D (x) the linear finite-element mass matrix: diagonal blocks D (l_{i-1} + l_i) / 3, off-diagonal
blocks D l_i / 6, block tridiagonal, symmetric positive definite when every l > 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit

from . import superhelix

RHO = 1.0  # sub-step bound: 2 (|a| h + |b| h^2) <= RHO
TOL = 1e-16  # relative truncation bound of each series
K_MAX = 48  # guard; with RHO = 1 the rule stops near 18
COMPLEX_STEP = 1e-30


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x such that [v]x a = v x a; v (..., 3) -> (..., 3, 3) (any dtype)."""
    out = np.zeros(v.shape[:-1] + (3, 3), dtype=v.dtype)
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


# --------------------------------------------------------------------------- data
@dataclass
class SuperClothoid(superhelix.PaddedRods):
    """A groom of Super Space Clothoids, padded to ``max_elements`` elements per strand.

    root_positions (S, 3), root_frames (S, 3, 3) with columns (n0 tangent, n1, n2), lengths (S, N) element
    lengths (0 for padding), curvatures (S, N + 1, 3) = q = (twist, kappa1, kappa2) at the **nodes**
    (0 beyond node n_elements), n_elements (S,).  Omega is linear between consecutive nodes.
    """

    def _curvatures(self, curvatures) -> np.ndarray:
        dtype = np.complex128 if np.iscomplexobj(curvatures) else np.float64
        S, N = self.lengths.shape
        return np.asarray(curvatures, dtype=dtype).reshape(S, N + 1, 3)

    @property
    def node_mask(self) -> np.ndarray:
        """(S, N + 1) True on real nodes (the degrees of freedom)."""
        return np.arange(self.max_elements + 1)[None, :] <= self.n_elements[:, None]

    def starts_and_slopes(self):
        """a_j = q_j and b_j = (q_{j+1} - q_j) / l_j per element, (S, N, 3) each (b = 0 on padding)."""
        q = self.curvatures
        l = self.lengths[..., None]
        safe = np.where(l > 0, l, 1.0)
        b = np.where(l > 0, (q[:, 1:] - q[:, :-1]) / safe, 0.0)
        return np.ascontiguousarray(q[:, :-1]), np.ascontiguousarray(b)

    def flat_offsets(self) -> np.ndarray:
        """(S + 1,) offsets of each strand's nodes in the flat node list."""
        return np.concatenate([[0], np.cumsum(self.n_elements + 1)]).astype(np.int64)

    def to_flat(self, padded: np.ndarray) -> np.ndarray:
        """(S, N + 1, ...) -> (V, ...) keeping real nodes only."""
        return padded[self.node_mask]

    def from_flat(self, flat: np.ndarray) -> np.ndarray:
        out = np.zeros((self.n_strands, self.max_elements + 1) + flat.shape[1:], dtype=flat.dtype)
        out[self.node_mask] = flat
        return out

    def subset(self, strand_ids) -> "SuperClothoid":
        ids = np.asarray(strand_ids, dtype=np.int64)
        n = int(self.n_elements[ids].max()) if len(ids) else 0
        return SuperClothoid(self.root_positions[ids], self.root_frames[ids], self.lengths[ids, :n],
                             self.curvatures[ids, :n + 1], self.n_elements[ids])


# --------------------------------------------------------------------------- series kernels
@njit(cache=True)
def _norm_real(x0, x1, x2):
    return np.sqrt(x0.real * x0.real + x1.real * x1.real + x2.real * x2.real)


@njit(cache=True)
def n_substeps(A, B, T):
    """Smallest m with 2 (A h + B h^2) <= RHO, h = T / m (m = 0 for T = 0)."""
    if T <= 0.0:
        return 0
    den = A + np.sqrt(A * A + 2.0 * B * RHO)
    if not (den > 0.0 and den < np.inf):  # zero, or NaN / inf curvatures: one step (the NaN propagates)
        return 1
    hmax = RHO / den
    m = int(np.ceil(T / hmax - 1e-12))
    return max(m, 1)


@njit(cache=True)
def n_terms(alpha, beta):
    """First K >= 1 whose tail bound 2 r max(d_K, d_{K-1}) / (1 - r) <= TOL, d the coefficients of
    exp(2 alpha x + beta x^2) ((k + 1) d_{k+1} = 2 alpha d_k + 2 beta d_{k-1}), r = 2 (alpha + beta) / (K + 1).
    Returns (K, bound)."""
    al = 2.0 * alpha
    be = 2.0 * beta
    dm1 = 1.0  # d_0
    d = al  # d_1
    K = 1
    while True:
        r = (al + be) / (K + 1)
        if r < 1.0:
            bound = 2.0 * r * max(d, dm1) / (1.0 - r)
            if bound <= TOL or K >= K_MAX:
                return K, bound
        elif K >= K_MAX or not (r < np.inf):  # NaN or inf rates: give up at the guard
            return K_MAX, np.inf
        dn = (al * d + be * dm1) / (K + 1)
        dm1 = d
        d = dn
        K += 1


@njit(cache=True)
def _mul_skew(M, w0, w1, w2, out, scale):
    """out += scale * M [w]x  (column c of M [w]x is M (w x e_c))."""
    for r in range(3):
        m0, m1, m2 = M[r, 0], M[r, 1], M[r, 2]
        out[r, 0] += scale * (m1 * w2 - m2 * w1)
        out[r, 1] += scale * (m2 * w0 - m0 * w2)
        out[r, 2] += scale * (m0 * w1 - m1 * w0)


@njit(cache=True)
def _mm_add(A, B, scale, out):
    """out += scale * A @ B (3x3)."""
    for r in range(3):
        for c in range(3):
            out[r, c] += scale * (A[r, 0] * B[0, c] + A[r, 1] * B[1, c] + A[r, 2] * B[2, c])


@njit(cache=True)
def _skew_mat(v, out):
    """out = [v]x (assigns)."""
    out[0, 0] = 0.0
    out[1, 1] = 0.0
    out[2, 2] = 0.0
    out[0, 1] = -v[2]
    out[0, 2] = v[1]
    out[1, 0] = v[2]
    out[1, 2] = -v[0]
    out[2, 0] = -v[1]
    out[2, 1] = v[0]


@njit(cache=True)
def _propagate(a, b, T, Phi, p, P, Mphi, MX, MZ, ser, mu, tmp):
    """Integrate Omega(t) = a + b t over [0, T] from Phi = I, p = P = 0 (module docstring).

    Outputs (assigned): Phi(T), p(T), P(T) = int_0^T p; Mphi[i] = int t^i Phi (i < 2), MX[i] = int t^i X
    (i < 3), MZ[i] = int t^i Z (i < 2), X = [p]x Phi, Z = [P]x Phi.  Scratch: ser (3, K_MAX + 6, 3, 3),
    mu (3, 3, 3, 3), tmp (4, 3, 3), all of the dtype of a.  Returns (sub-steps, largest K, largest bound).
    """
    for r in range(3):
        p[r] = 0.0
        P[r] = 0.0
        for c in range(3):
            Phi[r, c] = 1.0 if r == c else 0.0
            for i in range(2):
                Mphi[i, r, c] = 0.0
                MZ[i, r, c] = 0.0
            for i in range(3):
                MX[i, r, c] = 0.0
    A = max(_norm_real(a[0], a[1], a[2]),
            _norm_real(a[0] + b[0] * T, a[1] + b[1] * T, a[2] + b[2] * T))
    B = _norm_real(b[0], b[1], b[2])
    m = n_substeps(A, B, T)
    if m == 0:
        return 0, 0, 0.0
    h = T / m
    kmax = 0
    bmax = 0.0
    X0 = tmp[0]
    Z0 = tmp[1]
    Phi0 = tmp[2]
    W = tmp[3]
    for step in range(m):
        tau0 = step * h
        a0 = a[0] + b[0] * tau0
        a1 = a[1] + b[1] * tau0
        a2 = a[2] + b[2] * tau0
        K, bound = n_terms(_norm_real(a0, a1, a2) * h, B * h * h)
        kmax = max(kmax, K)
        bmax = max(bmax, bound)
        n = K + 5  # coefficients 0 .. K + 4: values need K + 2, first derivatives (complex step) K + 4
        ha0, ha1, ha2 = h * a0, h * a1, h * a2
        hb0, hb1, hb2 = h * h * b[0], h * h * b[1], h * h * b[2]
        # scaled coefficients Y_k h^k of Psi (ser[0]), xi (ser[1]), zeta (ser[2])
        for r in range(3):
            for c in range(3):
                ser[0, 0, r, c] = 1.0 if r == c else 0.0
                ser[1, 0, r, c] = 0.0
                ser[2, 0, r, c] = 0.0
        for k in range(n - 1):
            for y in range(3):
                for r in range(3):
                    for c in range(3):
                        ser[y, k + 1, r, c] = 0.0
            inv = 1.0 / (k + 1)
            for y in range(3):
                _mul_skew(ser[y, k], ha0, ha1, ha2, ser[y, k + 1], inv)
                if k >= 1:
                    _mul_skew(ser[y, k - 1], hb0, hb1, hb2, ser[y, k + 1], inv)
            # xi: + h Psi_k [e0]x ; zeta: + h xi_k
            for r in range(3):
                ser[1, k + 1, r, 1] += inv * h * ser[0, k, r, 2]
                ser[1, k + 1, r, 2] -= inv * h * ser[0, k, r, 1]
                for c in range(3):
                    ser[2, k + 1, r, c] += inv * h * ser[1, k, r, c]
        # values at h (mu[y, 0] reused later), moments mu[y, 1 + i] = int_0^h u^i Y, pi(h), Pi(h)
        for y in range(3):
            for i in range(3):
                for r in range(3):
                    for c in range(3):
                        mu[y, i, r, c] = 0.0
        # the values Y(h) go to the free slot ser[y, n]
        for y in range(3):
            for r in range(3):
                for c in range(3):
                    ser[y, n, r, c] = 0.0
        pi0 = np.zeros(3, dtype=p.dtype)
        Pi0 = np.zeros(3, dtype=p.dtype)
        for k in range(n - 1, -1, -1):  # small terms first
            for y in range(3):
                for r in range(3):
                    for c in range(3):
                        v = ser[y, k, r, c]
                        ser[y, n, r, c] += v
                        mu[y, 0, r, c] += v * (h / (k + 1))
                        mu[y, 1, r, c] += v * (h * h / (k + 2))
                        mu[y, 2, r, c] += v * (h * h * h / (k + 3))
            for r in range(3):
                pi0[r] += ser[0, k, r, 0] * (h / (k + 1))
                Pi0[r] += ser[0, k, r, 0] * (h * h / ((k + 1) * (k + 2)))
        # state at the sub-step start
        for r in range(3):
            for c in range(3):
                Phi0[r, c] = Phi[r, c]
                X0[r, c] = 0.0
                Z0[r, c] = 0.0
        _skew_mat(p, W)
        _mm_add(W, Phi0, 1.0, X0)
        _skew_mat(P, W)
        _mm_add(W, Phi0, 1.0, Z0)
        t1 = tau0
        t2 = tau0 * tau0
        # moments with weights 1, t, t^2 (t = tau0 + u), module docstring
        for r in range(3):
            for c in range(3):
                W[r, c] = mu[0, 0, r, c]
        _mm_add(Phi0, W, 1.0, Mphi[0])
        _mm_add(X0, W, 1.0, MX[0])
        _mm_add(Z0, W, 1.0, MZ[0])
        _mm_add(Phi0, W, t1, Mphi[1])
        _mm_add(X0, W, t1, MX[1])
        _mm_add(Z0, W, t1, MZ[1])
        _mm_add(X0, W, t2, MX[2])
        for r in range(3):
            for c in range(3):
                W[r, c] = mu[0, 1, r, c]  # int u Psi
        _mm_add(Phi0, W, 1.0, Mphi[1])
        _mm_add(X0, W, 1.0, MX[1])
        _mm_add(Z0, W, 1.0, MZ[1])
        _mm_add(X0, W, 2.0 * t1, MX[2])
        _mm_add(X0, W, 1.0, MZ[0])  # Z gets X0 u Psi
        _mm_add(X0, W, t1, MZ[1])
        for r in range(3):
            for c in range(3):
                W[r, c] = mu[0, 2, r, c]  # int u^2 Psi
        _mm_add(X0, W, 1.0, MX[2])
        _mm_add(X0, W, 1.0, MZ[1])
        for i in range(3):  # xi moments: X gets Phi0 xi
            for r in range(3):
                for c in range(3):
                    W[r, c] = mu[1, i, r, c]
            if i == 0:
                _mm_add(Phi0, W, 1.0, MX[0])
                _mm_add(Phi0, W, t1, MX[1])
                _mm_add(Phi0, W, t2, MX[2])
            elif i == 1:
                _mm_add(Phi0, W, 1.0, MX[1])
                _mm_add(Phi0, W, 2.0 * t1, MX[2])
            else:
                _mm_add(Phi0, W, 1.0, MX[2])
        for i in range(2):  # zeta moments: Z gets Phi0 zeta
            for r in range(3):
                for c in range(3):
                    W[r, c] = mu[2, i, r, c]
            if i == 0:
                _mm_add(Phi0, W, 1.0, MZ[0])
                _mm_add(Phi0, W, t1, MZ[1])
            else:
                _mm_add(Phi0, W, 1.0, MZ[1])
        # advance: P += h p + Phi0 Pi, p += Phi0 pi, Phi = Phi0 Psi(h)
        for r in range(3):
            dP = h * p[r]
            dp = 0.0 * p[r]
            for c in range(3):
                dP += Phi0[r, c] * Pi0[c]
                dp += Phi0[r, c] * pi0[c]
            P[r] += dP
            p[r] += dp
            for c in range(3):
                Phi[r, c] = 0.0
        _mm_add(Phi0, ser[0, n], 1.0, Phi)
    return m, kmax, bmax


@njit(cache=True)
def _propagate_state(a, b, T, Phi, p, ser):
    """Phi(T) and p(T) only (no auxiliary series, no moments): the same sub-steps, term counts and sums of
    Psi and pi as :func:`_propagate`, about a third of its work.  ser: scratch (K_MAX + 6, 3, 3)."""
    for r in range(3):
        p[r] = 0.0
        for c in range(3):
            Phi[r, c] = 1.0 if r == c else 0.0
    A = max(_norm_real(a[0], a[1], a[2]),
            _norm_real(a[0] + b[0] * T, a[1] + b[1] * T, a[2] + b[2] * T))
    B = _norm_real(b[0], b[1], b[2])
    m = n_substeps(A, B, T)
    if m == 0:
        return
    h = T / m
    Phi0 = np.empty((3, 3), dtype=Phi.dtype)
    pi0 = np.empty(3, dtype=p.dtype)
    for step in range(m):
        tau0 = step * h
        a0 = a[0] + b[0] * tau0
        a1 = a[1] + b[1] * tau0
        a2 = a[2] + b[2] * tau0
        K, bound = n_terms(_norm_real(a0, a1, a2) * h, B * h * h)
        n = K + 5
        ha0, ha1, ha2 = h * a0, h * a1, h * a2
        hb0, hb1, hb2 = h * h * b[0], h * h * b[1], h * h * b[2]
        for r in range(3):
            for c in range(3):
                ser[0, r, c] = 1.0 if r == c else 0.0
        for k in range(n - 1):
            for r in range(3):
                for c in range(3):
                    ser[k + 1, r, c] = 0.0
            inv = 1.0 / (k + 1)
            _mul_skew(ser[k], ha0, ha1, ha2, ser[k + 1], inv)
            if k >= 1:
                _mul_skew(ser[k - 1], hb0, hb1, hb2, ser[k + 1], inv)
        for r in range(3):
            pi0[r] = 0.0
            for c in range(3):
                ser[n, r, c] = 0.0
        for k in range(n - 1, -1, -1):  # small terms first, as in _propagate
            for r in range(3):
                for c in range(3):
                    ser[n, r, c] += ser[k, r, c]
                pi0[r] += ser[k, r, 0] * (h / (k + 1))
        for r in range(3):
            for c in range(3):
                Phi0[r, c] = Phi[r, c]
        for r in range(3):
            dp = 0.0 * p[r]
            for c in range(3):
                dp += Phi0[r, c] * pi0[c]
                Phi[r, c] = 0.0
            p[r] += dp
        _mm_add(Phi0, ser[n], 1.0, Phi)


@njit(cache=True)
def _state_kernel(a, b, strand, elem, t, Phi, p, ser):
    """Per point: the element's Phi(t), p(t) (:func:`_propagate_state`)."""
    for i in range(t.shape[0]):
        _propagate_state(a[strand[i], elem[i]], b[strand[i], elem[i]], t[i], Phi[i], p[i], ser)


def _scratch(dtype):
    return (np.empty((3, K_MAX + 6, 3, 3), dtype=dtype), np.empty((3, 3, 3, 3), dtype=dtype),
            np.empty((4, 3, 3), dtype=dtype))


@njit(cache=True)
def _element_kernel(l, a, b, Q, p, P, Mphi, MX, MZ, ser, mu, tmp, stats):
    """Every element over its full length (:func:`_propagate`); stats[s, j] = (sub-steps, K, bound)."""
    S, N = l.shape
    for s in range(S):
        for j in range(N):
            m, K, bound = _propagate(a[s, j], b[s, j], l[s, j], Q[s, j], p[s, j], P[s, j], Mphi[s, j],
                                     MX[s, j], MZ[s, j], ser, mu, tmp)
            stats[s, j, 0] = m
            stats[s, j, 1] = K
            stats[s, j, 2] = bound


@njit(cache=True)
def _chain(C0, R0, Q, p, C, R):
    """C_{j+1} = C_j + R_j p_j, R_{j+1} = R_j Q_j for every strand."""
    S, N = Q.shape[0], Q.shape[1]
    for s in range(S):
        for a in range(3):
            C[s, 0, a] = C0[s, a]
            for b in range(3):
                R[s, 0, a, b] = R0[s, a, b]
        for j in range(N):
            for a in range(3):
                acc = C[s, j, a]
                for b in range(3):
                    acc += R[s, j, a, b] * p[s, j, b]
                C[s, j + 1, a] = acc
                for b in range(3):
                    acc = 0.0 * acc
                    for k in range(3):
                        acc += R[s, j, a, k] * Q[s, j, k, b]
                    R[s, j + 1, a, b] = acc


# --------------------------------------------------------------------------- kinematics
@dataclass
class Kinematics:
    """Per element of one configuration: node positions C (S, N+1, 3) and frames R (S, N+1, 3, 3); in the
    element's start frame its end rotation Q = Phi(l), end position p, P = int p, and the moments
    Mphi (S, N, 2, 3, 3) = int t^i Phi, MX (S, N, 3, 3, 3) = int t^i [p]x Phi, MZ (S, N, 2, 3, 3) =
    int t^i [P]x Phi; a, b the element start values and slopes; stats (S, N, 3) = sub-steps, terms, bound."""

    clothoid: SuperClothoid
    C: np.ndarray
    R: np.ndarray
    Q: np.ndarray
    p: np.ndarray
    P: np.ndarray
    Mphi: np.ndarray
    MX: np.ndarray
    MZ: np.ndarray
    a: np.ndarray
    b: np.ndarray
    stats: np.ndarray


def kinematics(clothoid: SuperClothoid, moments: bool = True) -> Kinematics:
    """Node frames and positions by R_{j+1} = R_j Phi_j(l_j), C_{j+1} = C_j + R_j p_j(l_j), each element by
    sub-stepped power series (:func:`_propagate`); complex curvatures are carried through (complex step).
    ``moments=False``: frames and positions only (:func:`_propagate_state`, about 4x less work): enough for
    evaluate / sample, not for Jacobians, gravity or the mass matrix (P, Mphi, MX, MZ, stats are None)."""
    a, b = clothoid.starts_and_slopes()
    dtype = a.dtype
    l = np.ascontiguousarray(clothoid.lengths, dtype=np.float64)
    S, N = l.shape
    Q = np.empty((S, N, 3, 3), dtype=dtype)
    p = np.empty((S, N, 3), dtype=dtype)
    if moments:
        P = np.empty((S, N, 3), dtype=dtype)
        Mphi = np.empty((S, N, 2, 3, 3), dtype=dtype)
        MX = np.empty((S, N, 3, 3, 3), dtype=dtype)
        MZ = np.empty((S, N, 2, 3, 3), dtype=dtype)
        stats = np.empty((S, N, 3))
        _element_kernel(l, a, b, Q, p, P, Mphi, MX, MZ, *_scratch(dtype), stats)
    else:
        P = Mphi = MX = MZ = stats = None
        _state_kernel(a, b, np.repeat(np.arange(S, dtype=np.int64), N), np.tile(np.arange(N, dtype=np.int64), S),
                      l.ravel(), Q.reshape(S * N, 3, 3), p.reshape(S * N, 3), np.empty((K_MAX + 6, 3, 3), dtype=dtype))
    C = np.empty((S, N + 1, 3), dtype=dtype)
    R = np.empty((S, N + 1, 3, 3), dtype=dtype)
    _chain(np.ascontiguousarray(clothoid.root_positions, dtype=dtype),
           np.ascontiguousarray(clothoid.root_frames, dtype=dtype), Q, p, C, R)
    return Kinematics(clothoid, C, R, Q, p, P, Mphi, MX, MZ, a, b, stats)


def _with_moments(clothoid: SuperClothoid, kin: Kinematics | None) -> Kinematics:
    if kin is None:
        return kinematics(clothoid)
    if kin.Mphi is None:
        raise ValueError("these kinematics were computed with moments=False; derivatives and gravity need moments")
    return kin


def locate(clothoid: SuperClothoid, strand, s) -> tuple[np.ndarray, np.ndarray]:
    """Element index and local parameter t of arc length s on each strand (clamped to [0, L]): the
    Super-Helix's search (:func:`groomtool.rods.superhelix.locate`), the elements being laid out alike."""
    return superhelix.locate(clothoid, strand, s)


@njit(cache=True)
def _partial_kernel(a, b, strand, elem, t, Phi, p, Mphi, MX, ser, mu, tmp):
    """Per point: the element's state and moments over [0, t] (:func:`_propagate`)."""
    P = np.empty(3, dtype=p.dtype)
    MZ = np.empty((2, 3, 3), dtype=p.dtype)
    for i in range(t.shape[0]):
        _propagate(a[strand[i], elem[i]], b[strand[i], elem[i]], t[i], Phi[i], p[i], P, Mphi[i], MX[i], MZ,
                   ser, mu, tmp)


def _partial(clothoid: SuperClothoid, kin: Kinematics, strand, elem, t):
    n = len(t)
    dtype = kin.a.dtype
    Phi = np.empty((n, 3, 3), dtype=dtype)
    p = np.empty((n, 3), dtype=dtype)
    Mphi = np.empty((n, 2, 3, 3), dtype=dtype)
    MX = np.empty((n, 3, 3, 3), dtype=dtype)
    _partial_kernel(kin.a, kin.b, strand, elem, np.ascontiguousarray(t), Phi, p, Mphi, MX, *_scratch(dtype))
    return Phi, p, Mphi, MX


def evaluate(clothoid: SuperClothoid, strand, s, kin: Kinematics | None = None):
    """Positions (P, 3) and frames (P, 3, 3) at arc lengths s: C = C_e + R_e p(t), R = R_e Phi(t)."""
    kin = kin if kin is not None else kinematics(clothoid, moments=False)
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    elem, t = locate(clothoid, strand, s)
    dtype = kin.a.dtype
    Phi = np.empty((len(t), 3, 3), dtype=dtype)
    p = np.empty((len(t), 3), dtype=dtype)
    _state_kernel(kin.a, kin.b, strand, elem, np.ascontiguousarray(t), Phi, p,
                  np.empty((K_MAX + 6, 3, 3), dtype=dtype))
    Re = kin.R[strand, elem]
    return kin.C[strand, elem] + np.einsum("pab,pb->pa", Re, p), Re @ Phi


def evaluate_positions(clothoid: SuperClothoid, strand, s, kin: Kinematics | None = None) -> np.ndarray:
    """Positions (P, 3) at arc lengths s."""
    return evaluate(clothoid, strand, s, kin)[0]


def sample(clothoid: SuperClothoid, per_element: int = 4, kin: Kinematics | None = None):
    """Sample every strand at ``per_element`` equal steps per element (nodes included).

    Returns points (V, 3), offsets (S + 1,), strand id (V,) and arc length (V,).
    """
    kin = kin if kin is not None else kinematics(clothoid, moments=False)
    counts = clothoid.n_elements * per_element + 1
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    strand = np.repeat(np.arange(clothoid.n_strands), counts)
    local = np.arange(len(strand)) - offsets[strand]
    elem = np.minimum(local // per_element, np.maximum(clothoid.n_elements[strand] - 1, 0))
    frac = (local - elem * per_element) / per_element
    s = clothoid.element_starts[strand, elem] + frac * clothoid.lengths[strand, elem]
    return evaluate_positions(clothoid, strand, s, kin), offsets, strand, s


# --------------------------------------------------------------------------- point Jacobians
def _hat_split(M, l):
    """(int N_start W, int N_end W) from the moments int W, int t W of an element of length l
    (N_start = 1 - t/l, N_end = t/l); M (..., 2, 3, 3), l (...)."""
    inv = np.where(l > 0, 1.0 / np.where(l > 0, l, 1.0), 0.0)[..., None, None]
    end = M[..., 1, :, :] * inv
    return M[..., 0, :, :] - end, end


def node_jacobian_terms(kin: Kinematics):
    """Theta_i = sum_k R_k int_k N_i Phi and B_i = sum_k ([C_k]x R_k int_k N_i Phi + R_k int_k N_i X) over the
    whole elements k adjacent to node i; (S, N + 1, 3, 3) each, returned per element half:
    (Theta_start, Theta_end, B_start, B_end), (S, N, 3, 3) each (start: node k, end: node k + 1)."""
    l = kin.clothoid.lengths
    Ps, Pe = _hat_split(kin.Mphi, l)
    Xs, Xe = _hat_split(kin.MX[:, :, :2], l)
    Rk = kin.R[:, :-1]
    Ts, Te = Rk @ Ps, Rk @ Pe
    Ck = skew(kin.C[:, :-1])
    return Ts, Te, Ck @ Ts + Rk @ Xs, Ck @ Te + Rk @ Xe


class _PointTerms(NamedTuple):
    """What :func:`point_jacobians` and :func:`point_jacobians_rotation` share, per point: the element and its
    frame, Phi(t) on it, ``full`` (P, N, 1, 1) for the whole elements before the point, [x]x of the point
    (P, 1, 3, 3), the node terms of :func:`node_jacobian_terms` at the point's strand (P, N, 3, 3) and the hat
    splits of the point's own element over [0, t] with [p(t)]x."""

    elem: np.ndarray
    Re: np.ndarray
    Phi: np.ndarray
    full: np.ndarray
    xs: np.ndarray
    Ts: np.ndarray
    Te: np.ndarray
    Bs: np.ndarray
    Be: np.ndarray
    As: np.ndarray
    Ae: np.ndarray
    Ys: np.ndarray
    Ye: np.ndarray
    px: np.ndarray


def _point_terms(clothoid: SuperClothoid, strand, s, kin: Kinematics | None) -> _PointTerms:
    """The shared set-up of the point Jacobians (:class:`_PointTerms`)."""
    kin = _with_moments(clothoid, kin)
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    elem, t = locate(clothoid, strand, s)
    Phi, p, Mphi, MX = _partial(clothoid, kin, strand, elem, t)
    Re = kin.R[strand, elem]
    x = kin.C[strand, elem] + np.einsum("pab,pb->pa", Re, p)
    Ts, Te, Bs, Be = node_jacobian_terms(kin)
    full = (np.arange(clothoid.max_elements)[None, :] < elem[:, None])[..., None, None]
    le = clothoid.lengths[strand, elem]
    As, Ae = _hat_split(Mphi, le)
    Ys, Ye = _hat_split(MX[:, :2], le)
    return _PointTerms(elem, Re, Phi, full, skew(x)[:, None], Ts[strand], Te[strand], Bs[strand], Be[strand],
                       As, Ae, Ys, Ye, skew(p))


def _add_own_element(J: np.ndarray, pt: _PointTerms) -> None:
    """The point's own element e over [0, t]: R_e (int_0^t N_i X - [p(t)]x int_0^t N_i Phi), added to J."""
    idx = np.arange(len(pt.elem))
    J[idx, pt.elem] += pt.Re @ (pt.Ys - pt.px @ pt.As)
    J[idx, pt.elem + 1] += pt.Re @ (pt.Ye - pt.px @ pt.Ae)


def point_jacobians(clothoid: SuperClothoid, strand, s, kin: Kinematics | None = None):
    """dC(s)/dq for points on strands: (P, N + 1, 3, 3), block i = dC/dq_i (zero beyond the point's element).

    Whole elements k < e: [C_k - x]x R_k int N_i Phi + R_k int N_i X; the point's own element e over [0, t]:
    R_e (int_0^t N_i X - [p(t)]x int_0^t N_i Phi).  Also returns the element index of each point (P,).
    """
    pt = _point_terms(clothoid, strand, s, kin)
    Js = np.where(pt.full, pt.Bs - pt.xs @ pt.Ts, 0.0)
    Je = np.where(pt.full, pt.Be - pt.xs @ pt.Te, 0.0)
    J = np.zeros((len(pt.elem), clothoid.max_elements + 1, 3, 3), dtype=Js.dtype)
    J[:, :-1] += Js
    J[:, 1:] += Je
    _add_own_element(J, pt)
    return J, pt.elem


# --------------------------------------------------------------------------- energy and forces
def stiffness(clothoid: SuperClothoid, stiffness_diag):
    """K in banded form: diagonal blocks (S, N + 1, 3) = D (l_{i-1} + l_i) / 3 and off-diagonal blocks
    (S, N, 3) = D l_i / 6 coupling nodes i and i + 1 (D = (GJ, EI1, EI2); zero on padding)."""
    D = np.asarray(stiffness_diag, dtype=np.float64)
    l = clothoid.lengths
    lpad = np.concatenate([np.zeros((l.shape[0], 1)), l, np.zeros((l.shape[0], 1))], axis=1)
    diag = (lpad[:, :-1] + lpad[:, 1:])[..., None] * D / 3.0
    off = l[..., None] * D / 6.0
    return diag, off


def stiffness_matrix(clothoid: SuperClothoid, stiffness_diag) -> np.ndarray:
    """K dense, (S, 3(N + 1), 3(N + 1)), from :func:`stiffness`."""
    diag, off = stiffness(clothoid, stiffness_diag)
    S, N = clothoid.lengths.shape
    K = np.zeros((S, N + 1, 3, N + 1, 3))
    i = np.arange(N + 1)
    c = np.arange(3)
    K[:, i[:, None], c[None, :], i[:, None], c[None, :]] = diag
    j = np.arange(N)
    K[:, j[:, None], c[None, :], j[:, None] + 1, c[None, :]] = off
    K[:, j[:, None] + 1, c[None, :], j[:, None], c[None, :]] = off
    return K.reshape(S, 3 * (N + 1), 3 * (N + 1))


def stiffness_apply(clothoid: SuperClothoid, stiffness_diag, d: np.ndarray) -> np.ndarray:
    """K d for d (S, N + 1, 3), banded."""
    diag, off = stiffness(clothoid, stiffness_diag)
    out = diag * d
    out[:, :-1] += off * d[:, 1:]
    out[:, 1:] += off * d[:, :-1]
    return out


def stiffness_solve(clothoid: SuperClothoid, stiffness_diag, rhs: np.ndarray) -> np.ndarray:
    """K^{-1} rhs for rhs (S, N + 1, 3): K = D (x) M_FE decouples by component, so 3S tridiagonal systems
    M_FE x_c = rhs_c / D_c, solved by the Thomas algorithm (M_FE is SPD and diagonally dominant: no pivoting).
    Padding nodes (no element) get 0."""
    D = np.asarray(stiffness_diag, dtype=np.float64)
    l = clothoid.lengths
    S, N = l.shape
    lpad = np.concatenate([np.zeros((S, 1)), l, np.zeros((S, 1))], axis=1)
    diag = (lpad[:, :-1] + lpad[:, 1:]) / 3.0  # (S, N + 1)
    off = l / 6.0  # (S, N)
    real = diag > 0
    diag = np.where(real, diag, 1.0)
    b = np.where(real[..., None], np.asarray(rhs) / D, 0.0)
    c_prime = np.zeros((S, N))
    d_prime = np.empty_like(b)
    denom = diag[:, 0]
    d_prime[:, 0] = b[:, 0] / denom[:, None]
    for i in range(1, N + 1):
        c_prime[:, i - 1] = off[:, i - 1] / denom
        denom = diag[:, i] - off[:, i - 1] * c_prime[:, i - 1]
        d_prime[:, i] = (b[:, i] - off[:, i - 1, None] * d_prime[:, i - 1]) / denom[:, None]
    x = np.empty_like(b)
    x[:, N] = d_prime[:, N]
    for i in range(N - 1, -1, -1):
        x[:, i] = d_prime[:, i] - c_prime[:, i, None] * x[:, i + 1]
    return x


def rest_curvatures(clothoid: SuperClothoid, linear_density: float, gravity, stiffness_diag,
                    kin: Kinematics | None = None) -> np.ndarray:
    """The isolated inversion q0 = q - K^{-1} F(q) (docs/maths.md section 7; K block tridiagonal, not diagonal as
    for the helix), (S, N + 1, 3): the rest nodal curvatures for which the current shape is an equilibrium under
    gravity."""
    F = gravity_force(clothoid, linear_density, gravity, kin)
    return clothoid.curvatures - stiffness_solve(clothoid, stiffness_diag, F)


def elastic_energy(clothoid: SuperClothoid, rest_curvatures: np.ndarray, stiffness_diag) -> np.ndarray:
    """1/2 int (Omega - Omega0)^T D (Omega - Omega0) ds = 1/2 sum_j l_j/3 (d_j^2 + d_j d_{j+1} + d_{j+1}^2) . D."""
    d = clothoid.curvatures - rest_curvatures
    D = np.asarray(stiffness_diag, dtype=np.float64)
    quad = d[:, :-1] ** 2 + d[:, :-1] * d[:, 1:] + d[:, 1:] ** 2
    return 0.5 * np.einsum("sn,snk,k->s", clothoid.lengths / 3.0, quad, D)


def _element_integrals(kin: Kinematics):
    """int over each element of C, (S, N, 3): l C_k + R_k P_k."""
    l = kin.clothoid.lengths
    return l[..., None] * kin.C[:, :-1] + np.einsum("snab,snb->sna", kin.R[:, :-1], kin.P)


def gravity_potential(clothoid: SuperClothoid, linear_density: float, gravity, kin: Kinematics | None = None):
    """V = -rhoS g . int_0^L C(s) ds per strand (S,)."""
    kin = _with_moments(clothoid, kin)
    return -linear_density * np.einsum("snk,k->s", _element_integrals(kin), np.asarray(gravity, dtype=np.float64))


def _gravity_element_moments(kin: Kinematics):
    """Per element k: A0 = int f-matrix, A1 = int t f-matrix with f-matrix = [y0]x Phi - Z - (m + l) X + t X,
    y0 = R_k^T (M1_{k+1} - m C_k) + P_k(l), m = L - S_{k+1} (so R(tau)^T [Y]x = -f-matrix^T R_k^T)."""
    l = kin.clothoid.lengths
    integral = _element_integrals(kin)
    # M1_{k+1} = int_{s > S_{k+1}} C ds, m_{k+1} = L - S_{k+1}
    suffix = np.cumsum(integral[:, ::-1], axis=1)[:, ::-1]
    M1 = np.concatenate([suffix[:, 1:], np.zeros_like(suffix[:, :1])], axis=1)
    lsuf = np.cumsum(l[:, ::-1], axis=1)[:, ::-1]
    m = np.concatenate([lsuf[:, 1:], np.zeros_like(lsuf[:, :1])], axis=1)
    Rk = kin.R[:, :-1]
    y0 = np.einsum("snba,snb->sna", Rk, M1 - m[..., None] * kin.C[:, :-1]) + kin.P
    y0x = skew(y0)
    ml = (m + l)[..., None, None]
    A0 = y0x @ kin.Mphi[:, :, 0] - kin.MZ[:, :, 0] - ml * kin.MX[:, :, 0] + kin.MX[:, :, 1]
    A1 = y0x @ kin.Mphi[:, :, 1] - kin.MZ[:, :, 1] - ml * kin.MX[:, :, 1] + kin.MX[:, :, 2]
    return A0, A1


def gravity_force(clothoid: SuperClothoid, linear_density: float, gravity, kin: Kinematics | None = None):
    """F = -dV/dq = rhoS int N_i R^T (Y x g) ds as (S, N + 1, 3) (module docstring): per element k,
    int_k N f with f = -([y0]x Phi - Z - (m + l) X + t X)^T R_k^T g, y0 = R_k^T (M1_{k+1} - m C_k) + P_k(l)."""
    kin = _with_moments(clothoid, kin)
    g = np.asarray(gravity, dtype=np.float64)
    l = clothoid.lengths
    S, N = l.shape
    A0, A1 = _gravity_element_moments(kin)
    gam = np.einsum("snba,b->sna", kin.R[:, :-1], g)
    I0 = -np.einsum("snab,sna->snb", A0, gam)
    I1 = -np.einsum("snab,sna->snb", A1, gam)
    inv = np.where(l > 0, 1.0 / np.where(l > 0, l, 1.0), 0.0)[..., None]
    F = np.zeros((S, N + 1, 3), dtype=I0.dtype)
    F[:, :-1] += I0 - I1 * inv
    F[:, 1:] += I1 * inv
    return linear_density * F


@njit(cache=True)
def _element_subset_kernel(l, a, b, rows, elems, Q, p, P, Mphi, MX, MZ, ser, mu, tmp):
    """Recompute the listed (row, element) pairs only (:func:`_propagate`); elems < 0 are skipped."""
    for i in range(rows.shape[0]):
        r, j = rows[i], elems[i]
        if j < 0 or j >= l.shape[1]:
            continue
        _propagate(a[r, j], b[r, j], l[r, j], Q[r, j], p[r, j], P[r, j], Mphi[r, j], MX[r, j], MZ[r, j],
                   ser, mu, tmp)


def gravity_force_jacobian(clothoid: SuperClothoid, linear_density: float, gravity, kin: Kinematics | None = None,
                           chunk: int = 1024):
    """dF/dq per strand, (S, 3(N + 1), 3(N + 1)), by the complex step: column (i, c) = Im F(q + i eps e_ic) / eps
    (eps = 1e-30; exact to round-off since F is analytic in q); zero rows/columns on padding nodes.
    A node touches only its two elements: their series are recomputed in complex arithmetic, the other
    elements are copied from the real kinematics, then the chain and F (O(N) per column)."""
    kin = _with_moments(clothoid, kin)
    S, N = clothoid.lengths.shape
    n = 3 * (N + 1)
    out = np.zeros((S, n, n))
    sid_all, col_all = np.nonzero(np.arange(n)[None, :] // 3 <= clothoid.n_elements[:, None])
    l_all = np.ascontiguousarray(clothoid.lengths)
    scratch = _scratch(np.complex128)
    for start in range(0, len(sid_all), chunk):
        sid = sid_all[start:start + chunk]
        col = col_all[start:start + chunk]
        m = len(sid)
        q = clothoid.curvatures[sid].astype(np.complex128).reshape(m, n)
        q[np.arange(m), col] += 1j * COMPLEX_STEP
        sub = SuperClothoid(clothoid.root_positions[sid], clothoid.root_frames[sid], clothoid.lengths[sid],
                            q.reshape(m, N + 1, 3), clothoid.n_elements[sid])
        a, b = sub.starts_and_slopes()
        arrays = [np.ascontiguousarray(getattr(kin, name)[sid], dtype=np.complex128)
                  for name in ("Q", "p", "P", "Mphi", "MX", "MZ")]
        node = col // 3
        rows = np.repeat(np.arange(m, dtype=np.int64), 2)
        elems = np.stack([node - 1, node], axis=1).ravel().astype(np.int64)
        _element_subset_kernel(np.ascontiguousarray(l_all[sid]), a, b, rows, elems, *arrays, *scratch)
        Q, p, P, Mphi, MX, MZ = arrays
        C = np.empty((m, N + 1, 3), dtype=np.complex128)
        R = np.empty((m, N + 1, 3, 3), dtype=np.complex128)
        _chain(np.ascontiguousarray(sub.root_positions, dtype=np.complex128),
               np.ascontiguousarray(sub.root_frames, dtype=np.complex128), Q, p, C, R)
        ck = Kinematics(sub, C, R, Q, p, P, Mphi, MX, MZ, a, b, None)
        F = gravity_force(sub, linear_density, gravity, ck)
        out[sid, :, col] = F.reshape(m, n).imag / COMPLEX_STEP
    return out


def mass_matrix(clothoid: SuperClothoid, linear_density: float, kin: Kinematics | None = None, order: int = 8):
    """M = rhoS int (dC/dq)^T (dC/dq) ds per strand, (S, 3(N + 1), 3(N + 1)), Gauss-Legendre of ``order`` points
    per element (the integrand is smooth but not polynomial: a quadrature, not exact)."""
    kin = _with_moments(clothoid, kin)
    S, N = clothoid.lengths.shape
    xg, wg = np.polynomial.legendre.leggauss(order)
    xg = 0.5 * (xg + 1.0)
    wg = 0.5 * wg
    starts = clothoid.element_starts
    M = np.zeros((S, 3 * (N + 1), 3 * (N + 1)))
    strand = np.arange(S)
    for j in range(N):
        for xq, wq in zip(xg, wg):
            s = starts[:, j] + xq * clothoid.lengths[:, j]
            J, _ = point_jacobians(clothoid, strand, s, kin)
            J = J.transpose(0, 2, 1, 3).reshape(S, 3, 3 * (N + 1))
            weight = linear_density * wq * clothoid.lengths[:, j]
            M += weight[:, None, None] * np.einsum("sai,saj->sij", J, J)
    return M


# --------------------------------------------------------------------------- for the simulator (appended)
def point_jacobians_rotation(clothoid: SuperClothoid, strand, s, kin: Kinematics | None = None):
    """:func:`point_jacobians` together with the angular-velocity Jacobians and the frames (for the simulator's
    kinetic energy): returns (J, Jw, R, elem) with J = dC(s)/dq and Jw = dpsi(s)/dq, (P, N + 1, 3, 3) each, the
    frame R(s) (P, 3, 3) and the element index (P,).

    psi(s) = int_0^s R dOmega is the world rotation vector of the frame at s (module docstring), so with the hat
    functions, Jw_i(s) = int_0^s N_i R dtau: R_k int_k N_i Phi over the whole elements k before s (the Theta
    terms of :func:`node_jacobian_terms`) plus R_e int_0^t N_i Phi on the point's own element."""
    pt = _point_terms(clothoid, strand, s, kin)
    Tsp = np.where(pt.full, pt.Ts, 0.0)
    Tep = np.where(pt.full, pt.Te, 0.0)
    J = np.zeros((len(pt.elem), clothoid.max_elements + 1, 3, 3), dtype=Tsp.dtype)
    J[:, :-1] += np.where(pt.full, pt.Bs, 0.0) - pt.xs @ Tsp
    J[:, 1:] += np.where(pt.full, pt.Be, 0.0) - pt.xs @ Tep
    Jw = np.zeros_like(J)
    Jw[:, :-1] += Tsp
    Jw[:, 1:] += Tep
    _add_own_element(J, pt)
    idx = np.arange(len(pt.elem))
    Jw[idx, pt.elem] += pt.Re @ pt.As
    Jw[idx, pt.elem + 1] += pt.Re @ pt.Ae
    return J, Jw, pt.Re @ pt.Phi, pt.elem


def node_velocities(clothoid: SuperClothoid, rates: np.ndarray, kin: Kinematics | None = None) -> np.ndarray:
    """Velocities of the nodes (S, N + 1, 3) for nodal rates (S, N + 1, 3), root at rest, in O(N) per strand:
    Cdot(x) = sum over the elements k before x of (B_k - [x]x Theta_k) applied to the rates of the element's two
    nodes (:func:`node_jacobian_terms`), i.e. a prefix sum of beta_k = Bs_k v_k + Be_k v_{k+1} minus x cross the
    prefix sum of omega_k = Ts_k v_k + Te_k v_{k+1}."""
    kin = _with_moments(clothoid, kin)
    v = np.asarray(rates, dtype=np.float64).reshape(clothoid.curvatures.shape)
    Ts, Te, Bs, Be = node_jacobian_terms(kin)
    beta = np.einsum("snab,snb->sna", Bs, v[:, :-1]) + np.einsum("snab,snb->sna", Be, v[:, 1:])
    omega = np.einsum("snab,snb->sna", Ts, v[:, :-1]) + np.einsum("snab,snb->sna", Te, v[:, 1:])
    mask = clothoid.element_mask[..., None]
    S = clothoid.n_strands
    zero = np.zeros((S, 1, 3))
    B = np.concatenate([zero, np.cumsum(beta * mask, axis=1)], axis=1)
    W = np.concatenate([zero, np.cumsum(omega * mask, axis=1)], axis=1)
    return (B - np.cross(kin.C, W)) * clothoid.node_mask[..., None]
