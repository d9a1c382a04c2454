"""Super-Helix kinematics, gravity and their derivatives, batched over strands (docs/maths.md sections 1-2).

A strand is N helical elements of lengths l_j with constant material Darboux vectors
omega_j = q_j = (twist kappa0, kappa1, kappa2).  Frames are 3x3 matrices whose **columns** are
(n0, n1, n2) in world coordinates, n0 the tangent.  On element j, with t = s - S_j,

    R(s) = R_j exp(t [omega_j]x) = R_j Psi_0(t),      Psi_0(t) = I + c_1 W + c_2 W^2
    C(s) = C_j + R_j p_j(t),   p_j(t) = Psi_1(t) e0,  Psi_1(t) = t I + c_2 W + c_3 W^2
    int_0^t p_j = P_j(t) = Psi_2(t) e0,               Psi_2(t) = t^2/2 I + c_3 W + c_4 W^2

(W = [omega]x, c_n from :mod:`groomtool.rods.series`).  Strands are stored padded to the same
number of elements; a padding element has l = 0 and q = 0 and is the identity.

Derivatives (exact, explicit):
- a change d omega_k rotates everything beyond S_{k+1} by d theta = Theta_k d omega_k with
  Theta_k = int_{element k} R ds = R_k Psi_1(l_k), so for a point x beyond element k
      dC/domega_k = R_k D_k(l_k) + Theta_k dw x (x - C_{k+1})
                  = B_k - [x]x Theta_k,          B_k = R_k D_k(l_k) + [C_{k+1}]x Theta_k,
  D(t) = dp(t)/domega; inside its own element dC/domega_e = R_e D_e(t).
- gravity V = -rhoS g . int C ds, F = -dV/dq, F_k = rhoS G_k^T g with
      G_k = int dC/domega_k ds = R_k DP_k + m_{k+1} R_k D_k - [X_{k+1}]x Theta_k,
  m_{k+1} = L - S_{k+1} and X_{k+1} = int_{s > S_{k+1}} (C(s) - C_{k+1}) ds.
- dF/dq: off-diagonal blocks dF_j/domega_k = -rhoS Theta_j^T [g]x G_k (j < k), diagonal blocks
  the Hessian of rhoS u . (P_j + m_{j+1} p_j + Q_j Y_j) in omega_j (u = R_j^T g, Y_j = R_{j+1}^T X_{j+1}).
- point (dead) loads f_p at s_p: the Hessian of sum_p f_p . C(s_p) has the same form, blocks Theta_j^T A_k
  (j < k) with A_k from suffix sums of the loads beyond element k (:func:`point_load_hessian_parts`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from .series import _f23_point, _f_point, c_table

E0 = np.array([1.0, 0.0, 0.0])


# --------------------------------------------------------------------------- small algebra
def skew(v: np.ndarray) -> np.ndarray:
    """[v]x such that [v]x a = v x a; v (..., 3) -> (..., 3, 3)."""
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def _psi_apply(alpha, beta, gamma, omega, z, v):
    """(alpha I + beta W + gamma W^2) v = alpha v + beta w x v + gamma (w (w.v) - z v)."""
    wv = np.einsum("...i,...i->...", omega, v)
    return (alpha[..., None] * v + beta[..., None] * np.cross(omega, v)
            + gamma[..., None] * (omega * wv[..., None] - z[..., None] * v))


def _psi_apply_jacobian(beta, dbeta, gamma, dgamma, omega, z, v):
    """d/domega of (alpha I + beta(z) W + gamma(z) W^2) v, alpha constant; (..., 3, 3)."""
    wv = np.einsum("...i,...i->...", omega, v)
    wxv = np.cross(omega, v)
    w2v = omega * wv[..., None] - z[..., None] * v
    eye = np.eye(3)
    jac = -beta[..., None, None] * skew(v)
    jac += 2.0 * dbeta[..., None, None] * wxv[..., :, None] * omega[..., None, :]
    jac += gamma[..., None, None] * (omega[..., :, None] * v[..., None, :] + wv[..., None, None] * eye
                                     - 2.0 * v[..., :, None] * omega[..., None, :])
    jac += 2.0 * dgamma[..., None, None] * w2v[..., :, None] * omega[..., None, :]
    return jac


def local_position(t: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """p(t) = int_0^t exp(tau [omega]x) e0 dtau: the centreline in the element's start frame."""
    z = np.einsum("...i,...i->...", omega, omega)
    c, _, _ = c_table(t, z, order=0)
    e0 = np.broadcast_to(E0, omega.shape)
    return _psi_apply(t, c[2], c[3], omega, z, e0)


def local_position_jacobian(t: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """D(t) = dp(t)/domega, (..., 3, 3)."""
    z = np.einsum("...i,...i->...", omega, omega)
    c, dc, _ = c_table(t, z, order=1)
    e0 = np.broadcast_to(E0, omega.shape)
    return _psi_apply_jacobian(c[2], dc[2], c[3], dc[3], omega, z, e0)


# --------------------------------------------------------------------------- data
@dataclass
class PaddedRods:
    """What a groom of Super-Helices and one of Super Space Clothoids share: S strands padded to
    ``max_elements`` elements each, root positions (S, 3) and frames (S, 3, 3), element lengths (S, N) (0 for
    padding), curvatures (per element or per node: the model's ``_curvatures``) and n_elements (S,)."""

    root_positions: np.ndarray
    root_frames: np.ndarray
    lengths: np.ndarray
    curvatures: np.ndarray
    n_elements: np.ndarray = field(default=None)

    def __post_init__(self) -> None:
        self.root_positions = np.asarray(self.root_positions, dtype=np.float64).reshape(-1, 3)
        self.root_frames = np.asarray(self.root_frames, dtype=np.float64).reshape(-1, 3, 3)
        self.lengths = np.asarray(self.lengths, dtype=np.float64)
        if self.lengths.ndim == 1:
            self.lengths = self.lengths[None]
        self.curvatures = self._curvatures(self.curvatures)
        if self.n_elements is None:
            self.n_elements = np.count_nonzero(self.lengths > 0, axis=1)
        self.n_elements = np.asarray(self.n_elements, dtype=np.int64)

    def _curvatures(self, curvatures) -> np.ndarray:
        """The curvatures as the model stores them (dtype, shape from ``lengths``)."""
        raise NotImplementedError

    @property
    def n_strands(self) -> int:
        return self.lengths.shape[0]

    @property
    def max_elements(self) -> int:
        return self.lengths.shape[1]

    @property
    def element_mask(self) -> np.ndarray:
        """(S, N) True on real elements."""
        return np.arange(self.max_elements)[None, :] < self.n_elements[:, None]

    @property
    def element_starts(self) -> np.ndarray:
        """(S, N + 1) arc length S_j at each node."""
        return np.concatenate([np.zeros((self.n_strands, 1)), np.cumsum(self.lengths, axis=1)], axis=1)

    @property
    def strand_lengths(self) -> np.ndarray:
        return self.lengths.sum(axis=1)

    def with_curvatures(self, curvatures: np.ndarray):
        """The same strands with other curvatures (same model)."""
        return type(self)(self.root_positions, self.root_frames, self.lengths, curvatures, self.n_elements)


@dataclass
class SuperHelix(PaddedRods):
    """A groom of Super-Helices, padded to ``max_elements`` elements per strand.

    root_positions (S, 3), root_frames (S, 3, 3) with columns (n0 tangent, n1, n2),
    lengths (S, N) element lengths (0 for padding), curvatures (S, N, 3) = q = (twist, kappa1, kappa2)
    per element (0 for padding), n_elements (S,).
    """

    def _curvatures(self, curvatures) -> np.ndarray:
        return np.asarray(curvatures, dtype=np.float64).reshape(self.lengths.shape + (3,))

    # flat (unpadded) views: the generalised coordinates of all strands, strand after strand
    def flat_offsets(self) -> np.ndarray:
        """(S + 1,) offsets of each strand's elements in the flat element list."""
        return np.concatenate([[0], np.cumsum(self.n_elements)]).astype(np.int64)

    def to_flat(self, padded: np.ndarray) -> np.ndarray:
        """(S, N, ...) -> (E, ...) keeping real elements only."""
        return padded[self.element_mask]

    def from_flat(self, flat: np.ndarray) -> np.ndarray:
        out = np.zeros(self.lengths.shape + flat.shape[1:])
        out[self.element_mask] = flat
        return out

    def subset(self, strand_ids) -> "SuperHelix":
        ids = np.asarray(strand_ids, dtype=np.int64)
        n = int(self.n_elements[ids].max()) if len(ids) else 0
        return SuperHelix(self.root_positions[ids], self.root_frames[ids], self.lengths[ids, :n],
                          self.curvatures[ids, :n], self.n_elements[ids])


def map_strand_chunks(helix: SuperHelix, fn, chunk: int = 1024) -> np.ndarray:
    """Apply ``fn(sub_helix) -> (s, n, ...)`` to groups of strands of similar element counts, so each
    group is padded only to its own longest strand, and gather the results into (S, N, ...)."""
    order = np.argsort(helix.n_elements, kind="stable")
    out = None
    for start in range(0, helix.n_strands, chunk):
        ids = order[start:start + chunk]
        part = fn(helix.subset(ids))
        if out is None:
            out = np.zeros((helix.n_strands, helix.max_elements) + part.shape[2:])
        out[ids, :part.shape[1]] = part
    return out if out is not None else np.zeros(helix.lengths.shape + (3,))


# --------------------------------------------------------------------------- kinematics
@dataclass
class Kinematics:
    """Everything per element of one configuration, computed once and reused.

    C (S, N+1, 3) and R (S, N+1, 3, 3): node positions and frames; p, P (S, N, 3) end position and
    first moment of each element in its start frame; D, DP (S, N, 3, 3) their omega-derivatives; Theta (S, N, 3, 3) = R_j Psi_1(l_j); Q (S, N, 3, 3);
    c, dc (5, S, N) the coefficient table and its z-derivative.
    """

    helix: SuperHelix
    C: np.ndarray
    R: np.ndarray
    Q: np.ndarray
    p: np.ndarray
    P: np.ndarray
    D: np.ndarray
    DP: np.ndarray
    Theta: np.ndarray
    c: np.ndarray
    dc: np.ndarray
    z: np.ndarray


def kinematics(helix: SuperHelix) -> Kinematics:
    """Node frames and positions by the recursion R_{j+1} = R_j Q_j, C_{j+1} = C_j + R_j p_j, with the
    per-element closed forms (module docstring) evaluated in one compiled pass (:func:`_element_kernel`;
    tests/reference/rods.py has the vectorised numpy version the tests compare with)."""
    l = np.ascontiguousarray(helix.lengths, dtype=np.float64)
    w = np.ascontiguousarray(helix.curvatures, dtype=np.float64)
    S, N = l.shape
    z = np.empty((S, N))
    c = np.empty((5, S, N))
    dc = np.empty((5, S, N))
    Q = np.empty((S, N, 3, 3))
    psi1 = np.empty((S, N, 3, 3))
    p = np.empty((S, N, 3))
    P = np.empty((S, N, 3))
    D = np.empty((S, N, 3, 3))
    DP = np.empty((S, N, 3, 3))
    _element_kernel(l, w, z, c, dc, Q, psi1, p, P, D, DP)
    C = np.empty((S, N + 1, 3))
    R = np.empty((S, N + 1, 3, 3))
    _chain(np.ascontiguousarray(helix.root_positions), np.ascontiguousarray(helix.root_frames), Q, p, C, R, l)
    Theta = np.empty((S, N, 3, 3))
    _theta_kernel(R, psi1, Theta, l)
    return Kinematics(helix, C, R, Q, p, P, D, DP, Theta, c, dc, z)


@njit(cache=True)
def _e0_jacobian(beta, dbeta, gamma, dgamma, w0, w1, w2, z, out):
    """d/domega of (alpha I + beta(z) W + gamma(z) W^2) e0 (as _psi_apply_jacobian with v = e0):
    -beta [e0]x + 2 beta' (w x e0) w^T + gamma (w e0^T + w0 I - 2 e0 w^T) + 2 gamma' (w w0 - z e0) w^T."""
    w = (w0, w1, w2)
    wxv = (0.0, w2, -w1)
    w2v = (w0 * w0 - z, w1 * w0, w2 * w0)
    for a in range(3):
        for b in range(3):
            sk = 0.0
            if a == 1 and b == 2:
                sk = -1.0
            elif a == 2 and b == 1:
                sk = 1.0
            inner = w[a] * (1.0 if b == 0 else 0.0) + (w0 if a == b else 0.0) - 2.0 * (1.0 if a == 0 else 0.0) * w[b]
            out[a, b] = (-beta * sk + 2.0 * dbeta * wxv[a] * w[b] + gamma * inner
                         + 2.0 * dgamma * w2v[a] * w[b])


@njit(cache=True)
def _element_kernel(l, w, z, c, dc, Q, psi1, p, P, D, DP):
    """Per element: z = |omega|^2, c_n and dc_n/dz (series.c_table), Q = Psi_0(l), Psi_1(l),
    p = Psi_1(l) e0, P = Psi_2(l) e0, D = dp/domega, DP = dP/domega."""
    buf = np.empty((3, 5))
    W = np.empty((3, 3))
    W2 = np.empty((3, 3))
    _f_point(0.0, 1, buf)
    f0_at_zero = buf[0, 0]
    S, N = l.shape
    for s in range(S):
        for j in range(N):
            ti = l[s, j]
            w0, w1, w2 = w[s, j, 0], w[s, j, 1], w[s, j, 2]
            zz = w0 * w0 + w1 * w1 + w2 * w2
            z[s, j] = zz
            if ti == 0.0:
                # a zero-length element (the padding of shorter strands): what the general branch gives for l = 0
                # (to the sign of zeros), without the series
                c[0, s, j] = f0_at_zero
                for n in range(1, 5):
                    c[n, s, j] = 0.0
                for n in range(5):
                    dc[n, s, j] = 0.0
                for a in range(3):
                    p[s, j, a] = 0.0
                    P[s, j, a] = 0.0
                    for b in range(3):
                        Q[s, j, a, b] = 1.0 if a == b else 0.0
                        psi1[s, j, a, b] = 0.0
                        D[s, j, a, b] = 0.0
                        DP[s, j, a, b] = 0.0
                continue
            t2 = ti * ti
            _f_point(zz * t2, 1, buf)
            tn = 1.0
            for n in range(5):
                c[n, s, j] = tn * buf[0, n]
                dc[n, s, j] = tn * t2 * buf[1, n]
                tn *= ti
            c1, c2, c3, c4 = c[1, s, j], c[2, s, j], c[3, s, j], c[4, s, j]
            W[0, 0] = 0.0
            W[0, 1] = -w2
            W[0, 2] = w1
            W[1, 0] = w2
            W[1, 1] = 0.0
            W[1, 2] = -w0
            W[2, 0] = -w1
            W[2, 1] = w0
            W[2, 2] = 0.0
            for a in range(3):
                for b in range(3):
                    W2[a, b] = W[a, 0] * W[0, b] + W[a, 1] * W[1, b] + W[a, 2] * W[2, b]
            for a in range(3):
                for b in range(3):
                    eye = 1.0 if a == b else 0.0
                    Q[s, j, a, b] = eye + c1 * W[a, b] + c2 * W2[a, b]
                    psi1[s, j, a, b] = ti * eye + c2 * W[a, b] + c3 * W2[a, b]
                p[s, j, a] = psi1[s, j, a, 0]
            # P = (l^2/2) e0 + c3 w x e0 + c4 (w w0 - z e0)
            half = 0.5 * ti * ti
            P[s, j, 0] = half + c3 * 0.0 + c4 * (w0 * w0 - zz)
            P[s, j, 1] = c3 * w2 + c4 * (w1 * w0)
            P[s, j, 2] = c3 * (-w1) + c4 * (w2 * w0)
            _e0_jacobian(c2, dc[2, s, j], c3, dc[3, s, j], w0, w1, w2, zz, D[s, j])
            _e0_jacobian(c3, dc[3, s, j], c4, dc[4, s, j], w0, w1, w2, zz, DP[s, j])


@njit(cache=True)
def _theta_kernel(R, psi1, Theta, l):
    """Theta_j = R_j Psi_1(l_j) (zero for a zero-length element: Psi_1(0) = 0)."""
    S, N = psi1.shape[0], psi1.shape[1]
    for s in range(S):
        for j in range(N):
            if l[s, j] == 0.0:
                for a in range(3):
                    for b in range(3):
                        Theta[s, j, a, b] = 0.0
                continue
            for a in range(3):
                for b in range(3):
                    Theta[s, j, a, b] = (R[s, j, a, 0] * psi1[s, j, 0, b] + R[s, j, a, 1] * psi1[s, j, 1, b]
                                         + R[s, j, a, 2] * psi1[s, j, 2, b])


@njit(cache=True)
def _chain(C0, R0, Q, p, C, R, l):
    """C_{j+1} = C_j + R_j p_j, R_{j+1} = R_j Q_j for every strand (a zero-length element: p = 0, Q = I, copied)."""
    S, N = Q.shape[0], Q.shape[1]
    for s in range(S):
        for a in range(3):
            C[s, 0, a] = C0[s, a]
            for b in range(3):
                R[s, 0, a, b] = R0[s, a, b]
        for j in range(N):
            if l[s, j] == 0.0:
                for a in range(3):
                    C[s, j + 1, a] = C[s, j, a]
                    for b in range(3):
                        R[s, j + 1, a, b] = R[s, j, a, b]
                continue
            for a in range(3):
                acc = C[s, j, a]
                for b in range(3):
                    acc += R[s, j, a, b] * p[s, j, b]
                C[s, j + 1, a] = acc
                for b in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += R[s, j, a, k] * Q[s, j, k, b]
                    R[s, j + 1, a, b] = acc


def locate(helix: SuperHelix, strand, s) -> tuple[np.ndarray, np.ndarray]:
    """Element index and local parameter t of arc length s on each strand (clamped to [0, L])."""
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    s = np.ascontiguousarray(s, dtype=np.float64)
    elem = np.empty(len(s), dtype=np.int64)
    t = np.empty(len(s))
    _locate_kernel(np.ascontiguousarray(helix.element_starts), helix.n_elements, strand, s, elem, t)
    return elem, t


@njit(cache=True)
def _locate_kernel(starts, n_elements, strand, s, elem, t):
    for i in range(s.shape[0]):
        k = strand[i]
        n = max(n_elements[k], 1)
        lo, hi = 0, n - 1  # the last element whose start is <= s
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if starts[k, mid] <= s[i]:
                lo = mid
            else:
                hi = mid - 1
        elem[i] = lo
        t[i] = min(max(s[i] - starts[k, lo], 0.0), starts[k, lo + 1] - starts[k, lo])


def evaluate(helix: SuperHelix, strand, s, kin: Kinematics | None = None):
    """Positions (P, 3) and frames (P, 3, 3) at arc lengths s on the given strands."""
    kin = kin if kin is not None else kinematics(helix)
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    elem, t = locate(helix, strand, s)
    pos = np.empty((len(t), 3))
    frames = np.empty((len(t), 3, 3))
    _evaluate_kernel(kin.C, kin.R, np.ascontiguousarray(helix.curvatures), strand, elem, t, pos, frames)
    return pos, frames


@njit(cache=True)
def _evaluate_kernel(C, R, w, strand, elem, t, pos, frames):
    """C(s) = C_e + R_e (t e0 + c2 w x e0 + c3 w x (w x e0)), R(s) = R_e (I + c1 W + c2 W^2)."""
    buf = np.empty((3, 5))
    Q = np.empty((3, 3))
    p = np.empty(3)
    for i in range(t.shape[0]):
        k, e, ti = strand[i], elem[i], t[i]
        w0, w1, w2 = w[k, e, 0], w[k, e, 1], w[k, e, 2]
        z = w0 * w0 + w1 * w1 + w2 * w2
        t2 = ti * ti
        _f_point(z * t2, 0, buf)
        c1, c2, c3 = ti * buf[0, 1], t2 * buf[0, 2], t2 * ti * buf[0, 3]
        # W^2 = w w^T - z I
        Q[0, 0] = 1.0 + c2 * (w0 * w0 - z)
        Q[1, 1] = 1.0 + c2 * (w1 * w1 - z)
        Q[2, 2] = 1.0 + c2 * (w2 * w2 - z)
        Q[0, 1] = -c1 * w2 + c2 * w0 * w1
        Q[1, 0] = c1 * w2 + c2 * w0 * w1
        Q[0, 2] = c1 * w1 + c2 * w0 * w2
        Q[2, 0] = -c1 * w1 + c2 * w0 * w2
        Q[1, 2] = -c1 * w0 + c2 * w1 * w2
        Q[2, 1] = c1 * w0 + c2 * w1 * w2
        _place_point(C, R, k, e, ti, w0, w1, w2, z, c2, c3, p, pos[i])
        for a in range(3):
            for b in range(3):
                acc = 0.0
                for m in range(3):
                    acc += R[k, e, a, m] * Q[m, b]
                frames[i, a, b] = acc


@njit(cache=True)
def _place_point(C, R, k, e, ti, w0, w1, w2, z, c2, c3, p, out):
    """out = C_e + R_e p, p = t e0 + c2 (0, w2, -w1) + c3 (w0 w - z e0) (p: a 3-buffer)."""
    p[0] = ti + c3 * (w0 * w0 - z)
    p[1] = c2 * w2 + c3 * w0 * w1
    p[2] = -c2 * w1 + c3 * w0 * w2
    for a in range(3):
        acc = C[k, e, a]
        for b in range(3):
            acc += R[k, e, a, b] * p[b]
        out[a] = acc


def sample(helix: SuperHelix, per_element: int = 4, kin: Kinematics | None = None):
    """Sample every strand at ``per_element`` equal steps per element (nodes included).

    Returns points (V, 3), offsets (S + 1,), strand id (V,) and arc length (V,).
    """
    kin = kin if kin is not None else kinematics(helix)
    counts = helix.n_elements * per_element + 1
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    strand = np.repeat(np.arange(helix.n_strands), counts)
    local = np.arange(len(strand)) - offsets[strand]
    elem = np.minimum(local // per_element, np.maximum(helix.n_elements[strand] - 1, 0))
    frac = (local - elem * per_element) / per_element
    s = helix.element_starts[strand, elem] + frac * helix.lengths[strand, elem]
    return evaluate_positions(helix, strand, s, kin), offsets, strand, s


def evaluate_positions(helix: SuperHelix, strand, s, kin: Kinematics | None = None) -> np.ndarray:
    """Positions (P, 3) at arc lengths s on the given strands: :func:`evaluate` without the frames."""
    kin = kin if kin is not None else kinematics(helix)
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    elem, t = locate(helix, strand, s)
    pos = np.empty((len(t), 3))
    _position_kernel(kin.C, kin.R, np.ascontiguousarray(helix.curvatures), strand, elem, t, pos)
    return pos


@njit(cache=True)
def _position_kernel(C, R, w, strand, elem, t, pos):
    """C(s) = C_e + R_e (t e0 + c2 w x e0 + c3 w x (w x e0)), as in :func:`_evaluate_kernel`."""
    p = np.empty(3)
    for i in range(t.shape[0]):
        k, e, ti = strand[i], elem[i], t[i]
        w0, w1, w2 = w[k, e, 0], w[k, e, 1], w[k, e, 2]
        z = w0 * w0 + w1 * w1 + w2 * w2
        t2 = ti * ti
        f2, f3 = _f23_point(z * t2)
        _place_point(C, R, k, e, ti, w0, w1, w2, z, t2 * f2, t2 * ti * f3, p, pos[i])


def point_jacobians(helix: SuperHelix, strand, s, kin: Kinematics | None = None):
    """dC(s)/dq for points on strands: (P, N, 3, 3), block k = dC/domega_k (zero beyond the point).

    Also returns the element index of each point (P,).
    """
    kin = kin if kin is not None else kinematics(helix)
    strand = np.asarray(strand, dtype=np.int64)
    elem, t = locate(helix, strand, s)
    w = helix.curvatures[strand, elem]
    x = kin.C[strand, elem] + np.einsum("pab,pb->pa", kin.R[strand, elem], local_position(t, w))
    N = helix.max_elements
    theta = kin.Theta[strand]  # (P, N, 3, 3)
    B = kin.R[strand, :-1] @ kin.D[strand] + skew(kin.C[strand, 1:]) @ theta
    J = B - skew(x)[:, None] @ theta
    k = np.arange(N)[None, :]
    J[k > elem[:, None]] = 0.0
    own = kin.R[strand, elem] @ local_position_jacobian(t, w)
    J[np.arange(len(strand)), elem] = own
    return J, elem


def point_jacobian_parts(helix: SuperHelix, strand, s, kin: Kinematics | None = None):
    """The point-dependent pieces of :func:`point_jacobians` without the dense (P, N, 3, 3) array.

    Returns elem (P,), the points x = C(s) (P, 3) and the own-element blocks R_e D_e(t) (P, 3, 3);
    block k < elem of dC/dq is B_k - [x]x Theta_k with B from :func:`upstream_jacobian_terms`.
    Compiled, point by point (the numpy form, tests/reference/rods.py, took 0.6 s per 100k points).
    """
    kin = kin if kin is not None else kinematics(helix)
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    elem, t = locate(helix, strand, s)
    x = np.empty((len(strand), 3))
    own = np.empty((len(strand), 3, 3))
    _point_parts_kernel(kin.C, kin.R, helix.curvatures, strand, np.ascontiguousarray(elem, dtype=np.int64),
                        np.ascontiguousarray(t, dtype=np.float64), x, own)
    return elem, x, own


@njit(cache=True)
def _point_parts_kernel(C, R, w, strand, elem, t, x, own):
    """x_i = C_e + R_e p(t), own_i = R_e D(t) with p = t e0 + c2 w x e0 + c3 (w w0 - z e0) and D its
    omega-derivative (_e0_jacobian), c_n = t^n f_n(z t^2) and dc_n/dz = t^(n+2) f_n'(z t^2) (series.py)."""
    buf = np.empty((3, 5))
    p = np.empty(3)
    D = np.empty((3, 3))
    for i in range(strand.shape[0]):
        k, e, ti = strand[i], elem[i], t[i]
        w0, w1, w2 = w[k, e, 0], w[k, e, 1], w[k, e, 2]
        z = w0 * w0 + w1 * w1 + w2 * w2
        t2 = ti * ti
        _f_point(z * t2, 1, buf)
        c2, c3 = t2 * buf[0, 2], t2 * ti * buf[0, 3]
        dc2, dc3 = t2 * t2 * buf[1, 2], t2 * t2 * ti * buf[1, 3]
        _place_point(C, R, k, e, ti, w0, w1, w2, z, c2, c3, p, x[i])
        _e0_jacobian(c2, dc2, c3, dc3, w0, w1, w2, z, D)
        for a in range(3):
            for b in range(3):
                own[i, a, b] = R[k, e, a, 0] * D[0, b] + R[k, e, a, 1] * D[1, b] + R[k, e, a, 2] * D[2, b]


def upstream_jacobian_terms(kin: Kinematics) -> np.ndarray:
    """B_k = R_k D_k(l_k) + [C_{k+1}]x Theta_k per element, (S, N, 3, 3): dC/domega_k = B_k - [x]x Theta_k
    for a point x beyond element k."""
    return kin.R[:, :-1] @ kin.D + skew(kin.C[:, 1:]) @ kin.Theta


# --------------------------------------------------------------------------- energy and forces
def stiffness(helix: SuperHelix, stiffness_diag) -> np.ndarray:
    """K as (S, N, 3): K_j = l_j (GJ, EI1, EI2); zero on padding."""
    return helix.lengths[..., None] * np.asarray(stiffness_diag, dtype=np.float64)


def elastic_energy(helix: SuperHelix, rest_curvatures: np.ndarray, stiffness_diag) -> np.ndarray:
    """1/2 (q - q0)^T K (q - q0) per strand, (S,)."""
    d = helix.curvatures - rest_curvatures
    return 0.5 * np.einsum("snk,snk->s", stiffness(helix, stiffness_diag) * d, d)


def _downstream_moments(helix: SuperHelix, kin: Kinematics):
    """m_{j+1} = L - S_{j+1} (S, N) and X_{j+1} = int_{s > S_{j+1}} (C - C_{j+1}) ds (S, N, 3)."""
    l = helix.lengths
    integral = l[..., None] * kin.C[:, :-1] + np.einsum("snab,snb->sna", kin.R[:, :-1], kin.P)
    # first moment of everything beyond node j+1: sum over elements k > j
    m1 = np.cumsum(integral[:, ::-1], axis=1)[:, ::-1]
    m1_beyond = np.concatenate([m1[:, 1:], np.zeros_like(m1[:, :1])], axis=1)
    mass_beyond = np.cumsum(l[:, ::-1], axis=1)[:, ::-1]
    m_beyond = np.concatenate([mass_beyond[:, 1:], np.zeros_like(mass_beyond[:, :1])], axis=1)
    X = m1_beyond - m_beyond[..., None] * kin.C[:, 1:]
    return m_beyond, X, integral


def gravity_potential(helix: SuperHelix, linear_density: float, gravity, kin: Kinematics | None = None):
    """V = -rhoS g . int_0^L C(s) ds per strand (S,), exact."""
    kin = kin if kin is not None else kinematics(helix)
    _, _, integral = _downstream_moments(helix, kin)
    return -linear_density * np.einsum("snk,k->s", integral, np.asarray(gravity, dtype=np.float64))


def gravity_force(helix: SuperHelix, linear_density: float, gravity, kin: Kinematics | None = None):
    """F = -dV/dq = rhoS int (dC/dq)^T g ds = rhoS G_j^T g, as (S, N, 3), with the integrated Jacobians
    G_j = R_j DP_j + m_{j+1} R_j D_j - [X_{j+1}]x Theta_j (:func:`_downstream_moments`' m and X):

        F_j = rhoS (DP_j^T u_j + m_{j+1} D_j^T u_j + Theta_j^T (X_{j+1} x g)),   u_j = R_j^T g,

    one compiled pass from the tip (:func:`_gravity_force_kernel`)."""
    kin = kin if kin is not None else kinematics(helix)
    out = np.empty(helix.curvatures.shape)
    _gravity_force_kernel(np.ascontiguousarray(helix.lengths, dtype=np.float64), kin.C, kin.R, kin.P, kin.D, kin.DP,
                          kin.Theta, np.ascontiguousarray(gravity, dtype=np.float64), float(linear_density), out)
    return out


@njit(cache=True)
def _gravity_force_kernel(l, C, R, P, D, DP, Theta, g, rho, out):
    """:func:`gravity_force` per strand, j from the tip: m and m1 = int C ds of the elements beyond j,
    X = m1 - m C_{j+1}; then element j joins them (int_element C ds = l_j C_j + R_j P_j)."""
    S, N = l.shape
    for s in range(S):
        m = 0.0
        m10 = m11 = m12 = 0.0
        for j in range(N - 1, -1, -1):
            X0 = m10 - m * C[s, j + 1, 0]
            X1 = m11 - m * C[s, j + 1, 1]
            X2 = m12 - m * C[s, j + 1, 2]
            xg0 = X1 * g[2] - X2 * g[1]
            xg1 = X2 * g[0] - X0 * g[2]
            xg2 = X0 * g[1] - X1 * g[0]
            u0 = R[s, j, 0, 0] * g[0] + R[s, j, 1, 0] * g[1] + R[s, j, 2, 0] * g[2]
            u1 = R[s, j, 0, 1] * g[0] + R[s, j, 1, 1] * g[1] + R[s, j, 2, 1] * g[2]
            u2 = R[s, j, 0, 2] * g[0] + R[s, j, 1, 2] * g[1] + R[s, j, 2, 2] * g[2]
            for b in range(3):
                acc = (DP[s, j, 0, b] + m * D[s, j, 0, b]) * u0
                acc += (DP[s, j, 1, b] + m * D[s, j, 1, b]) * u1
                acc += (DP[s, j, 2, b] + m * D[s, j, 2, b]) * u2
                acc += Theta[s, j, 0, b] * xg0 + Theta[s, j, 1, b] * xg1 + Theta[s, j, 2, b] * xg2
                out[s, j, b] = rho * acc
            lj = l[s, j]
            m10 += lj * C[s, j, 0] + R[s, j, 0, 0] * P[s, j, 0] + R[s, j, 0, 1] * P[s, j, 1] + R[s, j, 0, 2] * P[s, j, 2]
            m11 += lj * C[s, j, 1] + R[s, j, 1, 0] * P[s, j, 0] + R[s, j, 1, 1] * P[s, j, 1] + R[s, j, 1, 2] * P[s, j, 2]
            m12 += lj * C[s, j, 2] + R[s, j, 2, 0] * P[s, j, 0] + R[s, j, 2, 1] * P[s, j, 1] + R[s, j, 2, 2] * P[s, j, 2]
            m += lj


def gravity_force_jacobian(helix: SuperHelix, linear_density: float, gravity, kin: Kinematics | None = None):
    """dF/dq per strand, (S, 3N, 3N), symmetric (F is a gradient): blocks U_j G_k above the diagonal,
    their transposes below, Dg_j on it (:func:`gravity_force_jacobian_parts`), written once each."""
    kin = kin if kin is not None else kinematics(helix)
    U, G, diag = gravity_force_jacobian_parts(helix, linear_density, gravity, kin)
    S, N = helix.lengths.shape
    full = np.empty((S, 3 * N, 3 * N))
    assemble_gravity_jacobian(U, G, diag, full)
    return full


def gravity_force_jacobian_parts(helix: SuperHelix, linear_density: float, gravity, kin: Kinematics):
    """The generators of dF/dq, each (S, N, 3, 3): U_j = -rhoS Theta_j^T [g]x and G_k (block (j, k) = U_j G_k
    for j < k, block (k, j) its transpose) and the diagonal blocks Dg_j, the Hessian of
    rhoS u . (P_j + m_{j+1} p_j + Q_j Y_j) in omega_j (module docstring); one compiled pass
    (:func:`_gravity_hessian_kernel`)."""
    g = np.asarray(gravity, dtype=np.float64)
    l = np.ascontiguousarray(helix.lengths, dtype=np.float64)
    S, N = l.shape
    c, dc, ddc = c_table(l, kin.z, order=2)
    U = np.empty((S, N, 3, 3))
    G = np.empty((S, N, 3, 3))
    diag = np.empty((S, N, 3, 3))
    _gravity_hessian_kernel(l, np.ascontiguousarray(helix.curvatures, dtype=np.float64), np.ascontiguousarray(kin.z),
                            np.ascontiguousarray(c), np.ascontiguousarray(dc), np.ascontiguousarray(ddc),
                            np.ascontiguousarray(kin.C), np.ascontiguousarray(kin.R), np.ascontiguousarray(kin.P),
                            np.ascontiguousarray(kin.D), np.ascontiguousarray(kin.DP), np.ascontiguousarray(kin.Theta),
                            g, float(linear_density), U, G, diag)
    return U, G, diag


@njit(cache=True)
def _form_hessian_add(k, beta, dbeta, ddbeta, gamma, dgamma, ddgamma, w, z, u, v, out):
    """out += k * the Hessian in omega of u . (alpha I + beta(z) W + gamma(z) W^2) v (the vectorised form is
    tests/reference/rods.py's psi_form_hessian)."""
    c0 = u[0] * v[0] + u[1] * v[1] + u[2] * v[2]
    c1 = (v[1] * u[2] - v[2] * u[1], v[2] * u[0] - v[0] * u[2], v[0] * u[1] - v[1] * u[0])
    uw = u[0] * w[0] + u[1] * w[1] + u[2] * w[2]
    vw = v[0] * w[0] + v[1] * w[1] + v[2] * w[2]
    wc1 = w[0] * c1[0] + w[1] * c1[1] + w[2] * c1[2]
    pz = uw * vw - z * c0
    gv = (u[0] * vw + v[0] * uw - 2.0 * c0 * w[0], u[1] * vw + v[1] * uw - 2.0 * c0 * w[1],
          u[2] * vw + v[2] * uw - 2.0 * c0 * w[2])
    kww = k * (4.0 * ddbeta * wc1 + 4.0 * ddgamma * pz)
    keye = k * (2.0 * dbeta * wc1 + 2.0 * dgamma * pz - 2.0 * gamma * c0)
    for a in range(3):
        for b in range(a + 1):  # symmetric: one computation per pair
            h = kww * (w[a] * w[b])
            h += k * 2.0 * dbeta * (w[a] * c1[b] + c1[a] * w[b])
            h += k * 2.0 * dgamma * (w[a] * gv[b] + gv[a] * w[b])
            h += k * gamma * (u[a] * v[b] + v[a] * u[b])
            if a == b:
                out[a, a] += h + keye
            else:
                out[a, b] += h
                out[b, a] += h


@njit(cache=True)
def _gravity_hessian_kernel(l, w, z, c, dc, ddc, C, R, P, D, DP, Theta, g, rho, U, G, diag):
    """Per element j (suffix sums from the tip): m = L - S_{j+1}, X = int_{s > S_{j+1}} (C - C_{j+1}) ds,
    G_j = R_j DP_j + m R_j D_j - [X]x Theta_j, U_j = -rho Theta_j^T [g]x, and diag_j = rho * the Hessian of
    u . (P_j + m p_j + Q_j Y) in omega_j, u = R_j^T g, Y = R_{j+1}^T X."""
    S, N = l.shape
    e0 = np.zeros(3)
    e0[0] = 1.0
    wj = np.empty(3)
    uj = np.empty(3)
    Yj = np.empty(3)
    hess = np.empty((3, 3))
    for s in range(S):
        m = 0.0
        m1 = np.zeros(3)  # first moment int C ds of the elements beyond j
        for j in range(N - 1, -1, -1):
            # X = m1 - m C_{j+1}
            X0 = m1[0] - m * C[s, j + 1, 0]
            X1 = m1[1] - m * C[s, j + 1, 1]
            X2 = m1[2] - m * C[s, j + 1, 2]
            for a in range(3):
                for b in range(3):
                    rdp = 0.0
                    rd = 0.0
                    for k in range(3):
                        rdp += R[s, j, a, k] * DP[s, j, k, b]
                        rd += R[s, j, a, k] * D[s, j, k, b]
                    # ([X]x Theta)_ab = (X x Theta[:, b])_a
                    if a == 0:
                        xt = X1 * Theta[s, j, 2, b] - X2 * Theta[s, j, 1, b]
                    elif a == 1:
                        xt = X2 * Theta[s, j, 0, b] - X0 * Theta[s, j, 2, b]
                    else:
                        xt = X0 * Theta[s, j, 1, b] - X1 * Theta[s, j, 0, b]
                    G[s, j, a, b] = rdp + m * rd - xt
            # U_j[a, c] = -rho (Theta_j^T [g]x)[a, c] = -rho (Theta[:, a] . (g x e_c)) = -rho (Theta[:, a] x g)_c
            for a in range(3):
                t0, t1, t2 = Theta[s, j, 0, a], Theta[s, j, 1, a], Theta[s, j, 2, a]
                U[s, j, a, 0] = -rho * (t1 * g[2] - t2 * g[1])
                U[s, j, a, 1] = -rho * (t2 * g[0] - t0 * g[2])
                U[s, j, a, 2] = -rho * (t0 * g[1] - t1 * g[0])
            for a in range(3):
                wj[a] = w[s, j, a]
                uj[a] = R[s, j, 0, a] * g[0] + R[s, j, 1, a] * g[1] + R[s, j, 2, a] * g[2]
                Yj[a] = R[s, j + 1, 0, a] * X0 + R[s, j + 1, 1, a] * X1 + R[s, j + 1, 2, a] * X2
            for a in range(3):
                for b in range(3):
                    hess[a, b] = 0.0
            zj = z[s, j]
            _form_hessian_add(1.0, c[3, s, j], dc[3, s, j], ddc[3, s, j], c[4, s, j], dc[4, s, j], ddc[4, s, j],
                              wj, zj, uj, e0, hess)
            _form_hessian_add(m, c[2, s, j], dc[2, s, j], ddc[2, s, j], c[3, s, j], dc[3, s, j], ddc[3, s, j],
                              wj, zj, uj, e0, hess)
            _form_hessian_add(1.0, c[1, s, j], dc[1, s, j], ddc[1, s, j], c[2, s, j], dc[2, s, j], ddc[2, s, j],
                              wj, zj, uj, Yj, hess)
            for a in range(3):
                for b in range(3):
                    diag[s, j, a, b] = rho * hess[a, b]
            # add element j to the moments beyond j - 1: int_element C ds = l C_j + R_j P_j
            lj = l[s, j]
            for a in range(3):
                m1[a] += (lj * C[s, j, a] + R[s, j, a, 0] * P[s, j, 0] + R[s, j, a, 1] * P[s, j, 1]
                          + R[s, j, a, 2] * P[s, j, 2])
            m += lj


@njit(cache=True)
def assemble_gravity_jacobian(U, G, diag, out):
    """out[s] = the dense 3N x 3N matrix with blocks U_j G_k (j < k), (U_k G_j)^T (j > k), diag_j (j = k),
    written row after row."""
    S, N = U.shape[0], U.shape[1]
    for s in range(S):
        for r in range(N):
            for a in range(3):
                row = 3 * r + a
                g0, g1, g2 = G[s, r, 0, a], G[s, r, 1, a], G[s, r, 2, a]
                for j in range(r):  # (U_j G_r)^T: entry (a, b) = U_j[b] . G_r[:, a]
                    for b in range(3):
                        out[s, row, 3 * j + b] = U[s, j, b, 0] * g0 + U[s, j, b, 1] * g1 + U[s, j, b, 2] * g2
                for b in range(3):
                    out[s, row, 3 * r + b] = diag[s, r, a, b]
                u0, u1, u2 = U[s, r, a, 0], U[s, r, a, 1], U[s, r, a, 2]
                for k in range(r + 1, N):
                    for b in range(3):
                        out[s, row, 3 * k + b] = u0 * G[s, k, 0, b] + u1 * G[s, k, 1, b] + u2 * G[s, k, 2, b]


# --------------------------------------------------------------------------- point (dead) loads: the Hessian
def point_load_hessian_parts(helix: SuperHelix, strand, s, f, kin: Kinematics | None = None):
    """The generators of the Hessian in q of Phi = sum_p f_p . C(s_p; q) (world point loads f_p at fixed arc
    lengths s_p on strands ``strand``), each (S, N, 3, 3), in the form of :func:`gravity_force_jacobian_parts`:
    block (j, k) = U_j A_k for j < k (U_j = Theta_j^T), block (k, j) its transpose, diag_k on the diagonal.

    With J_pk = dC(s_p)/domega_k (R_k D_k - [x_p - C_{k+1}]x Theta_k beyond element k, R_k D_k(t_p) inside it)
    and dg_k/domega_j = sum_p J_pk^T [f_p]x Theta_j for j < k (a change of omega_j moves everything beyond
    S_{j+1} rigidly, rotating J_pk by Theta_j domega_j):

        A_k    = -[F_k]x R_k D_k + (N_k^T - tr(N_k) I) Theta_k - sum_{e_p = k} [f_p]x R_k D_k(t_p),
        diag_k = Hess_omega_k [ u . Psi_1(l_k) e0 + sum_c M[:, c] . Psi_0(l_k) e_c + sum_{e_p = k} u_p . Psi_1(t_p) e0 ]

    F_k = sum_{e_p > k} f_p, N_k = sum_{e_p > k} f_p (x_p - C_{k+1})^T (suffix sums from the tip), u = R_k^T F_k,
    M = R_k^T N_k R_{k+1}, u_p = R_k^T f_p (e_p, t_p: the element and local parameter of s_p, as
    :func:`locate`; a load at a node S_k belongs to element k with t = 0).  Each diagonal term is a form
    u . (alpha I + beta W + gamma W^2) v (:func:`_form_hessian_add`), at the partial length t_p for the loads
    inside the element.  O(S N + P), one compiled pass (:func:`_point_load_hessian_kernel`)."""
    kin = kin if kin is not None else kinematics(helix)
    l = np.ascontiguousarray(helix.lengths, dtype=np.float64)
    S, N = l.shape
    c, dc, ddc = c_table(l, kin.z, order=2)
    U = np.zeros((S, N, 3, 3))
    A = np.zeros((S, N, 3, 3))
    diag = np.zeros((S, N, 3, 3))
    strand = np.ascontiguousarray(strand, dtype=np.int64)
    elem, t = locate(helix, strand, s)
    _point_load_hessian_kernel(l, np.ascontiguousarray(helix.curvatures, dtype=np.float64), np.ascontiguousarray(kin.z),
                               np.ascontiguousarray(c), np.ascontiguousarray(dc), np.ascontiguousarray(ddc),
                               np.ascontiguousarray(kin.C), np.ascontiguousarray(kin.R), np.ascontiguousarray(kin.D),
                               np.ascontiguousarray(kin.Theta), helix.n_elements, strand,
                               np.ascontiguousarray(elem, dtype=np.int64), np.ascontiguousarray(t, dtype=np.float64),
                               np.ascontiguousarray(f, dtype=np.float64).reshape(-1, 3), U, A, diag)
    return U, A, diag


@njit(cache=True)
def _point_load_hessian_kernel(l, w, z, c, dc, ddc, C, R, D, Theta, n_elements, strand, elem, t, f, U, A, diag):
    """Bin the loads per element (force, f (x - C_0)^T, the own-element blocks of A and diag), then one pass
    from each strand's tip with the suffix sums F_k, N_k (point_load_hessian_parts)."""
    S, N = l.shape
    Fe = np.zeros((S, N, 3))
    Ne = np.zeros((S, N, 3, 3))  # sum_{e_p = e} f_p (x_p - C_0)^T
    buf = np.empty((3, 5))
    p = np.empty(3)
    x = np.empty(3)
    Dt = np.empty((3, 3))
    RD = np.empty((3, 3))
    wj = np.empty(3)
    up = np.empty(3)
    e0 = np.zeros(3)
    e0[0] = 1.0
    for i in range(strand.shape[0]):
        k, e, ti = strand[i], elem[i], t[i]
        if e >= n_elements[k]:  # a strand without elements
            continue
        w0, w1, w2 = w[k, e, 0], w[k, e, 1], w[k, e, 2]
        zz = w0 * w0 + w1 * w1 + w2 * w2
        t2 = ti * ti
        _f_point(zz * t2, 2, buf)
        c2, c3 = t2 * buf[0, 2], t2 * ti * buf[0, 3]
        dc2, dc3 = t2 * t2 * buf[1, 2], t2 * t2 * ti * buf[1, 3]
        ddc2, ddc3 = t2 * t2 * t2 * buf[2, 2], t2 * t2 * t2 * ti * buf[2, 3]
        # the point relative to the root: x - C_0 = (C_e - C_0) + R_e p(t)
        p[0] = ti + c3 * (w0 * w0 - zz)
        p[1] = c2 * w2 + c3 * w0 * w1
        p[2] = -c2 * w1 + c3 * w0 * w2
        f0, f1, f2 = f[i, 0], f[i, 1], f[i, 2]
        for a in range(3):
            x[a] = C[k, e, a] - C[k, 0, a] + R[k, e, a, 0] * p[0] + R[k, e, a, 1] * p[1] + R[k, e, a, 2] * p[2]
            up[a] = R[k, e, 0, a] * f0 + R[k, e, 1, a] * f1 + R[k, e, 2, a] * f2
            wj[a] = w[k, e, a]
        Fe[k, e, 0] += f0
        Fe[k, e, 1] += f1
        Fe[k, e, 2] += f2
        for a in range(3):
            for b in range(3):
                Ne[k, e, a, b] += f[i, a] * x[b]
        # own-element block of A: -[f]x R_e D(t); ([f]x M)[:, b] = f x M[:, b]
        _e0_jacobian(c2, dc2, c3, dc3, w0, w1, w2, zz, Dt)
        for a in range(3):
            for b in range(3):
                RD[a, b] = R[k, e, a, 0] * Dt[0, b] + R[k, e, a, 1] * Dt[1, b] + R[k, e, a, 2] * Dt[2, b]
        for b in range(3):
            A[k, e, 0, b] -= f1 * RD[2, b] - f2 * RD[1, b]
            A[k, e, 1, b] -= f2 * RD[0, b] - f0 * RD[2, b]
            A[k, e, 2, b] -= f0 * RD[1, b] - f1 * RD[0, b]
        # own-element diagonal term: the Hessian of u_p . Psi_1(t) e0
        _form_hessian_add(1.0, c2, dc2, ddc2, c3, dc3, ddc3, wj, zz, up, e0, diag[k, e])
    F = np.empty(3)
    Nk = np.empty((3, 3))
    Nr = np.empty((3, 3))
    T = np.empty((3, 3))
    M = np.empty((3, 3))
    RN = np.empty((3, 3))
    u = np.empty(3)
    col = np.empty(3)
    ec = np.empty(3)
    for s in range(S):
        F[:] = 0.0
        Nr[:, :] = 0.0
        for j in range(n_elements[s] - 1, -1, -1):
            # N_k = sum_{e_p > k} f_p (x_p - C_{k+1})^T = Nr - F (C_{k+1} - C_0)^T
            for a in range(3):
                for b in range(3):
                    Nk[a, b] = Nr[a, b] - F[a] * (C[s, j + 1, b] - C[s, 0, b])
            tr = Nk[0, 0] + Nk[1, 1] + Nk[2, 2]
            for a in range(3):
                for b in range(3):
                    T[a, b] = Nk[b, a] - (tr if a == b else 0.0)
            for a in range(3):
                for b in range(3):
                    RD[a, b] = R[s, j, a, 0] * D[s, j, 0, b] + R[s, j, a, 1] * D[s, j, 1, b] + R[s, j, a, 2] * D[s, j, 2, b]
            for b in range(3):
                for a in range(3):
                    A[s, j, a, b] += T[a, 0] * Theta[s, j, 0, b] + T[a, 1] * Theta[s, j, 1, b] + T[a, 2] * Theta[s, j, 2, b]
                A[s, j, 0, b] -= F[1] * RD[2, b] - F[2] * RD[1, b]
                A[s, j, 1, b] -= F[2] * RD[0, b] - F[0] * RD[2, b]
                A[s, j, 2, b] -= F[0] * RD[1, b] - F[1] * RD[0, b]
            for a in range(3):
                for b in range(3):
                    U[s, j, a, b] = Theta[s, j, b, a]
            # diagonal: u . Psi_1(l) e0 with u = R_j^T F, and sum_c M[:, c] . Psi_0(l) e_c with M = R_j^T N R_{j+1}
            for a in range(3):
                u[a] = R[s, j, 0, a] * F[0] + R[s, j, 1, a] * F[1] + R[s, j, 2, a] * F[2]
                wj[a] = w[s, j, a]
            for a in range(3):
                for b in range(3):
                    RN[a, b] = R[s, j, 0, a] * Nk[0, b] + R[s, j, 1, a] * Nk[1, b] + R[s, j, 2, a] * Nk[2, b]
            for a in range(3):
                for b in range(3):
                    M[a, b] = RN[a, 0] * R[s, j + 1, 0, b] + RN[a, 1] * R[s, j + 1, 1, b] + RN[a, 2] * R[s, j + 1, 2, b]
            zj = z[s, j]
            _form_hessian_add(1.0, c[2, s, j], dc[2, s, j], ddc[2, s, j], c[3, s, j], dc[3, s, j], ddc[3, s, j],
                              wj, zj, u, e0, diag[s, j])
            for cc in range(3):
                for a in range(3):
                    col[a] = M[a, cc]
                    ec[a] = 1.0 if a == cc else 0.0
                _form_hessian_add(1.0, c[1, s, j], dc[1, s, j], ddc[1, s, j], c[2, s, j], dc[2, s, j], ddc[2, s, j],
                                  wj, zj, col, ec, diag[s, j])
            # element j joins the loads beyond j - 1
            for a in range(3):
                F[a] += Fe[s, j, a]
                for b in range(3):
                    Nr[a, b] += Ne[s, j, a, b]


def mass_matrix(helix: SuperHelix, linear_density: float, kin: Kinematics | None = None, order: int = 4):
    """M = rhoS int (dC/dq)^T (dC/dq) ds per strand, (S, 3N, 3N), Gauss-Legendre of ``order`` per element."""
    kin = kin if kin is not None else kinematics(helix)
    S, N = helix.lengths.shape
    xg, wg = np.polynomial.legendre.leggauss(order)
    xg = 0.5 * (xg + 1.0)
    wg = 0.5 * wg
    starts = helix.element_starts
    M = np.zeros((S, 3 * N, 3 * N))
    strand = np.arange(S)
    for j in range(N):
        for xq, wq in zip(xg, wg):
            s = starts[:, j] + xq * helix.lengths[:, j]
            J, _ = point_jacobians(helix, strand, s, kin)
            J = J.transpose(0, 2, 1, 3).reshape(S, 3, 3 * N)
            weight = linear_density * wq * helix.lengths[:, j]
            M += weight[:, None, None] * np.einsum("sai,saj->sij", J, J)
    return M
