"""The circular helix through two co-helical point-tangent pairs, batched (docs/maths.md section 4.1).

Given unit tangents t0, t1 and a chord c = P1 - P0 with c . (t1 - t0) = 0, find the world rotation
vector Phi = l Omega and the arc length l of the helix starting at P0 along t0 and ending at P1 along t1:

    exp([Phi]x) t0 = t1,      c = l (I + f2(|Phi|^2) [Phi]x + f3(|Phi|^2) [Phi]x^2) t0.

**Reduction to one unknown.**  Any axis a taking t0 to t1 by a rotation is equidistant from them, so
a lies in the plane Pi orthogonal to n = (t1 - t0) / |t1 - t0|; so do the bisector m = t0 + t1 and
(by co-helicity) the chord.  With d = |t1 - t0| / 2, e = n x a, the half winding h and the angle
alpha between a and t0 follow in closed form from the axis alone:

    cos alpha = a . m/2,   sin alpha cos h = e . m/2,   sin alpha sin h = d
    =>  h = atan2(d, e . m/2),   and the helix chord is  c / l = (a . m/2) a + (d / h) e.

Parametrise a = cos(phi) b1 + sin(phi) b2 in Pi (b2 = m/|m|, b1 = b2 x n: phi = 0 is the minimal
rotation, a planar circular arc).  The chord direction must match the angle gamma of c in Pi:

    F(phi) = atan2(d, h(phi) (a . m/2)) - (gamma - phi) = 0,      phi in (gamma - pi, gamma).

F is negative at the left end, positive at the right end and strictly increasing (F' >= d^2/3,
checked numerically over the whole circle), so **the root is unique**: for a given pair there is
exactly one interpolating helix with winding 2h in (0, 2 pi), no free parameter.  It is found by a
bracketed Newton iteration (bisection fallback) to round-off.  Then Phi = 2 h a and
l = |c| / sqrt((a . m/2)^2 + (d/h)^2).

Nearly straight pieces (d < 1e-9, chord within 1e-6 rad of m): the direction n is then known only to
~1e-16/d, and the twist (the axis tilt phi, tan(phi) ~ 3 delta / d^2 for a chord-bisector angle delta)
is amplified noise; the minimal rotation (phi = 0: a planar arc, least twist, l = |c| h / sin h) is
returned instead, with a chord error |c| delta.  Up to d < 1e-6 F is still flat to O(d^2) ~ round-off
over most of the bracket and its root can be lost (a full turn returned for a straight piece): there
both the helix and the arc are computed and the one whose chord is closer to c is kept.  t1 = t0 to round-off (d < 1e-15) with the chord off
t0: one full turn about c (Phi = 2 pi c/|c|, l = |c| / (t0 . c/|c|)).  t1 = -t0 (m = 0): b2 is
taken along the chord, and the same equation gives the half turn about t0 x c.

:func:`solve_helix` and :func:`solve_chain` run numba kernels, one element at a time, with the
operations of the array versions ``solve_helix_numpy`` / ``solve_chain_numpy`` (the tests' references,
in tests/reference/fit.py).
The kernels call libm's arctan2 and arcsin; numpy may use its own SIMD versions (it does with
AVX-512), which differ in the last bit: the results then agree to round-off, not bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .kernels import cross, dot, f123, f123_s, sinc_s

_TINY = 1e-300
STRAIGHT_D = 1e-9        # d below this and chord along t0 + t1: a planar arc (twist undetermined)
NEAR_STRAIGHT_D = 1e-6   # d below this and chord along t0 + t1: the helix or the arc, whichever meets the chord
FLAT_D = 1e-15           # d below this: t1 == t0 to round-off, the plane Pi is undefined
ANTIPODAL_M = 1e-8       # |t0 + t1| below this: t1 == -t0, the bisector is not a direction


@dataclass
class HelixSolution:
    """Per element: ``phi`` (E, 3) world rotation vector l * Omega, ``length`` (E,) arc length,
    ``iterations`` (E,) Newton/bisection steps, ``kind`` (E,) 0 general, 1 nearly straight (planar arc),
    2 full turn, 3 no helix (t1 == t0, chord not ahead of t0: a straight element is returned)."""

    phi: np.ndarray
    length: np.ndarray
    iterations: np.ndarray
    kind: np.ndarray


def solve_helix(t0, t1, chord, chord_tolerance=None, max_iter: int = 100) -> HelixSolution:
    """Solve exp([Phi]x) t0 = t1, chord = l (I + f2 [Phi]x + f3 [Phi]x^2) t0 for (Phi, l), batched.

    t0, t1, chord (E, 3); the tangents are normalised here.  The chord should satisfy co-helicity;
    its component along t1 - t0 is ignored (it cannot be matched) and shows in :func:`helix_residuals`.

    ``chord_tolerance`` (scalar or (E,), metres; default exact): a noise gate on the twist.  Where the
    planar arc (phi = 0, the minimal rotation: least twist) misses the chord direction by at most
    chord_tolerance / |c| rad (|F(0)| below that), it is taken (gamma shifted by F(0)); elsewhere the
    exact helix.  The end tangent stays exact and the chord length is matched.  (Trimming the twist
    of the other elements down to the tolerance instead was tried: it biases the element lengths,
    shortening curly strands by ~0.4 %.)
    """
    t0 = np.ascontiguousarray(np.asarray(t0, dtype=np.float64).reshape(-1, 3))
    t1 = np.ascontiguousarray(np.asarray(t1, dtype=np.float64).reshape(-1, 3))
    chord = np.ascontiguousarray(np.asarray(chord, dtype=np.float64).reshape(-1, 3))
    E = len(t0)
    gated = chord_tolerance is not None
    budget = np.ascontiguousarray(np.broadcast_to(np.asarray(chord_tolerance if gated else 0.0,
                                                             dtype=np.float64), (E,)))
    out = HelixSolution(np.zeros((E, 3)), np.zeros(E), np.zeros(E, dtype=np.int64), np.zeros(E, dtype=np.int64))
    _solve_flat(t0, t1, chord, budget, gated, max_iter, out.phi, out.length, out.iterations, out.kind)
    return out


def rotate(phi, v):
    """exp([Phi]x) v = v + f1 Phi x v + f2 Phi x (Phi x v), f_n = f_n(|Phi|^2)."""
    f1, f2, _ = f123(dot(phi, phi))
    pv = cross(phi, v)
    return v + f1[..., None] * pv + f2[..., None] * cross(phi, pv)


def helix_chord(phi, length, t0):
    """l (I + f2 [Phi]x + f3 [Phi]x^2) t0: the chord of the helix of rotation Phi and length l."""
    _, f2, f3 = f123(dot(phi, phi))
    pv = cross(phi, t0)
    return length[..., None] * (t0 + f2[..., None] * pv + f3[..., None] * cross(phi, pv))


def helix_residuals(phi, length, t0, t1, chord):
    """Max-norm residuals per element: |exp([Phi]x) t0 - t1| and |helix chord - chord|."""
    rt = np.abs(rotate(phi, t0) - t1).max(axis=-1)
    rc = np.abs(helix_chord(phi, length, t0) - chord).max(axis=-1)
    return rt, rc


def solve_chain(P, T, n_elements, chord_tolerance, max_iter: int = 100) -> HelixSolution:
    """Helices along strands, planar arcs where within tolerance, with error feedback; flat (E,).

    P, T (S, N+1, 3) padded points and tangents, n_elements (S,), chord_tolerance (S,) metres.
    Element i aims at P_{i+1} from the node C_i actually reached: C_{i+1} = C_i + chord(Phi_i, l_i, t_i)
    with (Phi_i, l_i) the helix of (t_i, t_{i+1}) for the chord P_{i+1} - C_i within the tolerance,
    so the chord deviations do not accumulate along the strand.
    """
    P = np.ascontiguousarray(P, dtype=np.float64)
    T = np.ascontiguousarray(T, dtype=np.float64)
    n_elements = np.ascontiguousarray(n_elements, dtype=np.int64)
    tol = np.ascontiguousarray(np.broadcast_to(np.asarray(chord_tolerance, dtype=np.float64), (len(P),)))
    E = int(n_elements.sum())
    out = HelixSolution(np.zeros((E, 3)), np.zeros(E), np.zeros(E, dtype=np.int64), np.zeros(E, dtype=np.int64))
    _chain_kernel(P, T, n_elements, tol, max_iter, out.phi, out.length, out.iterations, out.kind)
    return out


# --------------------------------------------------------------------------- numba kernels
@njit(cache=True, error_model="numpy")
def _max_s(a, b):
    """np.maximum on scalars (NaN propagates)."""
    return a if (a >= b or a != a) else b


@njit(cache=True, error_model="numpy")
def _F_s(phi, d, mb1, mb2, gamma):
    """F(phi) and F'(phi) (above; the reference's ``_F``) on scalars."""
    return _F_cs(np.cos(phi), np.sin(phi), phi, d, mb1, mb2, gamma)


@njit(cache=True, error_model="numpy")
def _F_cs(c, s, phi, d, mb1, mb2, gamma):
    """:func:`_F_s` with c = cos(phi), s = sin(phi) given."""
    ma = c * mb1 + s * mb2
    me = c * mb2 - s * mb1
    h = np.arctan2(d, me)
    H = h * ma
    dh = d * ma / (d * d + me * me)
    dH = dh * ma + h * me
    F = np.arctan2(d, H) - gamma + phi
    dF = 1.0 - d * dH / (d * d + H * H)
    return F, dF


@njit(cache=True, error_model="numpy")
def _unit_s(a0, a1, a2):
    """v / max(|v|, tiny), as the reference's ``_unit``."""
    nrm = _max_s(np.sqrt(a0 * a0 + a1 * a1 + a2 * a2), _TINY)
    return a0 / nrm, a1 / nrm, a2 / nrm


@njit(cache=True, error_model="numpy")
def _solve_one(a0, a1, a2, b0, b1, b2, c0, c1, c2, budget, gated, max_iter, k, phi, length, iterations, kind):
    """One element of the reference ``solve_helix_numpy`` (same operations), written at index k; the tangents
    a = t0, b = t1 normalised by :func:`_unit_s`."""
    n0, n1, n2 = b0 - a0, b1 - a1, b2 - a2
    D = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    nrm = _max_s(D, _TINY)
    n0, n1, n2 = n0 / nrm, n1 / nrm, n2 / nrm
    d = 0.5 * D
    cl = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    nrm = _max_s(cl, _TINY)
    h0, h1, h2 = c0 / nrm, c1 / nrm, c2 / nrm
    m0, m1, m2 = a0 + b0, a1 + b1, a2 + b2
    mlen = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    nrm = _max_s(mlen, _TINY)
    along = h0 * (m0 / nrm) + h1 * (m1 / nrm) + h2 * (m2 / nrm) >= 1.0 - 5e-13
    iterations[k] = 0
    if d < STRAIGHT_D and along:
        _planar_arc(a0, a1, a2, b0, b1, b2, d, cl, k, phi, length, kind)
        return
    if d < FLAT_D:
        cos_a = h0 * a0 + h1 * a1 + h2 * a2
        if cos_a > 1e-12:
            w = 2.0 * np.pi
            phi[k, 0], phi[k, 1], phi[k, 2] = w * h0, w * h1, w * h2
            length[k] = cl / cos_a
            kind[k] = 2
        else:
            phi[k, 0], phi[k, 1], phi[k, 2] = 0.0, 0.0, 0.0
            length[k] = cl
            kind[k] = 3
        return
    # general case
    cn = c0 * n0 + c1 * n1 + c2 * n2
    p0, p1, p2 = c0 - cn * n0, c1 - cn * n1, c2 - cn * n2          # chord projected on Pi
    if mlen < ANTIPODAL_M:
        nrm = _max_s(np.sqrt(p0 * p0 + p1 * p1 + p2 * p2), _TINY)
        e0, e1, e2 = p0 / nrm, p1 / nrm, p2 / nrm
    else:
        e0, e1, e2 = m0 / nrm, m1 / nrm, m2 / nrm
    # b2 = e, b1 = b2 x n
    f0, f1, f2 = e1 * n2 - e2 * n1, e2 * n0 - e0 * n2, e0 * n1 - e1 * n0
    hm0, hm1, hm2 = 0.5 * m0, 0.5 * m1, 0.5 * m2
    mb1 = hm0 * f0 + hm1 * f1 + hm2 * f2
    mb2 = hm0 * e0 + hm1 * e1 + hm2 * e2
    gamma = np.arctan2(p0 * e0 + p1 * e1 + p2 * e2, p0 * f0 + p1 * f1 + p2 * f2)
    if gated:
        angle = budget / _max_s(np.sqrt(p0 * p0 + p1 * p1 + p2 * p2), _TINY)
        F0, _ = _F_cs(1.0, 0.0, 0.0, d, mb1, mb2, gamma)          # cos(0), sin(0) exactly
        gamma = gamma + (F0 if np.abs(F0) <= angle else 0.0)
    lo, hi = gamma - np.pi, gamma
    M2 = _max_s(1.0 - d * d, 0.0)
    x = np.arctan2(3.0 * M2 * (gamma - 0.5 * np.pi), d * d)
    if not (x > lo and x < hi):
        x = gamma - 0.5 * np.pi
    its = 0
    for _ in range(max_iter):
        F, dF = _F_s(x, d, mb1, mb2, gamma)
        if F < 0.0:
            lo = x
        else:
            hi = x
        step = F / _max_s(dF, _TINY)
        xn = x - step
        tol = 2e-16 * (1.0 + np.abs(x))
        done = (np.abs(step) <= tol) or (hi - lo <= 2.0 * tol)
        if not ((xn > lo and xn < hi) or done):
            xn = 0.5 * (lo + hi)
        x = xn
        its += 1
        if done:
            break
    cx, sx = np.cos(x), np.sin(x)
    u0, u1, u2 = cx * f0 + sx * e0, cx * f1 + sx * e1, cx * f2 + sx * e2     # the axis a
    v0, v1, v2 = n1 * u2 - n2 * u1, n2 * u0 - n0 * u2, n0 * u1 - n1 * u0     # e = n x a
    ma = hm0 * u0 + hm1 * u1 + hm2 * u2
    me = hm0 * v0 + hm1 * v1 + hm2 * v2
    h = np.arctan2(d, me)
    w = 2.0 * h
    phi[k, 0], phi[k, 1], phi[k, 2] = w * u0, w * u1, w * u2
    length[k] = np.sqrt(p0 * p0 + p1 * p1 + p2 * p2) / np.sqrt(ma * ma + (d / h) ** 2)
    iterations[k] = its
    kind[k] = 0
    if d < NEAR_STRAIGHT_D and along:
        # F is flat to O(d^2) here and its root can be lost in round-off: keep the arc if it meets the chord better
        x0, x1, x2 = phi[k, 0], phi[k, 1], phi[k, 2]
        l = length[k]
        _planar_arc(a0, a1, a2, b0, b1, b2, d, cl, k, phi, length, kind)
        if _chord_error_s(phi[k, 0], phi[k, 1], phi[k, 2], length[k], a0, a1, a2, c0, c1, c2) \
                >= _chord_error_s(x0, x1, x2, l, a0, a1, a2, c0, c1, c2):
            phi[k, 0], phi[k, 1], phi[k, 2] = x0, x1, x2
            length[k] = l
            kind[k] = 0


@njit(cache=True, error_model="numpy")
def _planar_arc(a0, a1, a2, b0, b1, b2, d, cl, k, phi, length, kind):
    """The minimal rotation (least twist) from a = t0 to b = t1: a planar arc of winding 2 asin(d) about
    t0 x t1 and chord l sin(h)/h = |c|, written at index k."""
    x0, x1, x2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
    nrm = _max_s(np.sqrt(x0 * x0 + x1 * x1 + x2 * x2), _TINY)
    h = np.arcsin(min(d, 1.0))
    w = 2.0 * h
    phi[k, 0], phi[k, 1], phi[k, 2] = w * (x0 / nrm), w * (x1 / nrm), w * (x2 / nrm)
    length[k] = cl / sinc_s(h / np.pi)
    kind[k] = 1


@njit(cache=True, error_model="numpy")
def _chord_error_s(x0, x1, x2, l, t0, t1, t2, c0, c1, c2):
    """|helix_chord(Phi, l, t0) - c|^2 for one element (the operations of :func:`helix_chord`)."""
    _, f2, f3 = f123_s(x0 * x0 + x1 * x1 + x2 * x2)
    q0, q1, q2 = x1 * t2 - x2 * t1, x2 * t0 - x0 * t2, x0 * t1 - x1 * t0
    r0, r1, r2 = x1 * q2 - x2 * q1, x2 * q0 - x0 * q2, x0 * q1 - x1 * q0
    e0 = l * (t0 + f2 * q0 + f3 * r0) - c0
    e1 = l * (t1 + f2 * q1 + f3 * r1) - c1
    e2 = l * (t2 + f2 * q2 + f3 * r2) - c2
    return e0 * e0 + e1 * e1 + e2 * e2


@njit(cache=True, error_model="numpy")
def _solve_flat(t0, t1, chord, budget, gated, max_iter, phi, length, iterations, kind):
    """:func:`solve_helix` on flat (E, 3) arrays."""
    for k in range(t0.shape[0]):
        a0, a1, a2 = _unit_s(t0[k, 0], t0[k, 1], t0[k, 2])
        b0, b1, b2 = _unit_s(t1[k, 0], t1[k, 1], t1[k, 2])
        _solve_one(a0, a1, a2, b0, b1, b2, chord[k, 0], chord[k, 1], chord[k, 2], budget[k], gated, max_iter,
                   k, phi, length, iterations, kind)


@njit(cache=True, error_model="numpy")
def _chain_kernel(P, T, n_elements, tol, max_iter, phi, length, iterations, kind):
    """:func:`solve_chain`: per strand, element after element from the node reached."""
    k = 0
    for s in range(P.shape[0]):
        C0, C1, C2 = P[s, 0, 0], P[s, 0, 1], P[s, 0, 2]
        b0, b1, b2 = _unit_s(T[s, 0, 0], T[s, 0, 1], T[s, 0, 2])
        for i in range(n_elements[s]):
            a0, a1, a2 = b0, b1, b2                                  # t_i normalised once
            b0, b1, b2 = _unit_s(T[s, i + 1, 0], T[s, i + 1, 1], T[s, i + 1, 2])
            _solve_one(a0, a1, a2, b0, b1, b2, P[s, i + 1, 0] - C0, P[s, i + 1, 1] - C1, P[s, i + 1, 2] - C2,
                       tol[s], True, max_iter, k, phi, length, iterations, kind)
            # C += l (t + f2 Phi x t + f3 Phi x (Phi x t)), as helix_chord
            x0, x1, x2 = phi[k, 0], phi[k, 1], phi[k, 2]
            t0, t1, t2 = T[s, i, 0], T[s, i, 1], T[s, i, 2]
            _, f2, f3 = f123_s(x0 * x0 + x1 * x1 + x2 * x2)
            q0, q1, q2 = x1 * t2 - x2 * t1, x2 * t0 - x0 * t2, x0 * t1 - x1 * t0
            r0, r1, r2 = x1 * q2 - x2 * q1, x2 * q0 - x0 * q2, x0 * q1 - x1 * q0
            l = length[k]
            C0 += l * (t0 + f2 * q0 + f3 * r0)
            C1 += l * (t1 + f2 * q1 + f3 * r1)
            C2 += l * (t2 + f2 * q2 + f3 * r2)
            k += 1
