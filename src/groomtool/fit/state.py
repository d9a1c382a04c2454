"""From per-element world rotations to the Super-Helix state (docs/maths.md section 4.4).

Root frame R_0 = (n0, n1, n2) with n0 = t_0 and n1 the component orthogonal to t_0 of the world axis
least aligned with t_0, normalised; n2 = n0 x n1.  Then along the strand

    R_{j+1} = exp([Phi_j]x) R_j  (= R_j exp(l_j [omega_j]x)),    omega_j = q_j = R_j^T Phi_j / l_j,

so the frame is continuous at every joint and the curve is G1 by construction.  Node positions use
the same closed form as :mod:`groomtool.rods.superhelix`:

    C_{j+1} = C_j + l_j (I + f2 [Phi_j]x + f3 [Phi_j]x^2) t_j,     f_n = f_n(|Phi_j|^2).

:func:`assemble` runs a numba kernel (strand by strand); ``assemble_numpy`` (tests/reference/fit.py) is
the array version it reproduces (the 3x3 products with fused multiply-adds, as numpy's matmul through OpenBLAS).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from ..rods.superhelix import SuperHelix
from .kernels import cross, dot, f123_s, fma


def root_frames(tangents) -> np.ndarray:
    """R_0 (S, 3, 3), columns (t, n1, n2): n1 from the world axis least aligned with t."""
    t = np.asarray(tangents, dtype=np.float64).reshape(-1, 3)
    t = t / np.linalg.norm(t, axis=1)[:, None]
    ref = np.zeros_like(t)
    ref[np.arange(len(t)), np.argmin(np.abs(t), axis=1)] = 1.0
    n1 = ref - dot(ref, t)[:, None] * t
    n1 /= np.linalg.norm(n1, axis=1)[:, None]
    n2 = cross(t, n1)
    return np.stack([t, n1, n2], axis=2)


@dataclass
class CurveTable:
    """A fitted groom as flat elements, for fast point queries (all in world coordinates).

    elem_offsets (S+1,); per element: start (E,) arc length, length (E,), C (E, 3) start point,
    T (E, 3) start tangent, Omega (E, 3) world Darboux vector; strand_length (S,).
    """

    elem_offsets: np.ndarray
    start: np.ndarray
    length: np.ndarray
    C: np.ndarray
    T: np.ndarray
    Omega: np.ndarray
    strand_length: np.ndarray


def assemble(root_positions, root_tangents, phi, lengths, n_elements, frames=None):
    """SuperHelix from roots, world rotations Phi (S, N, 3) and lengths (S, N) (padding: l = 0, Phi = 0).

    ``frames`` (S, 3, 3): root frames to use (their first column should be the root tangent);
    default :func:`root_frames`.  Returns (helix, table), ``table`` a :class:`CurveTable` of the curve.
    """
    lengths = np.asarray(lengths, dtype=np.float64)
    n_elements = np.asarray(n_elements, dtype=np.int64)
    S, N = lengths.shape
    mask = np.arange(N)[None, :] < n_elements[:, None]
    phi = np.asarray(phi, dtype=np.float64).reshape(S, N, 3)
    return assemble_flat(root_positions, root_tangents, phi[mask], lengths[mask], n_elements, N, frames)


def assemble_flat(root_positions, root_tangents, phi, lengths, n_elements, max_elements=None, frames=None):
    """:func:`assemble` from flat per-element Phi (E, 3) and lengths (E,), strand after strand; the
    SuperHelix is padded to ``max_elements`` (default: the longest strand)."""
    n_elements = np.ascontiguousarray(n_elements, dtype=np.int64)
    S = len(n_elements)
    N = int(n_elements.max(initial=0)) if max_elements is None else int(max_elements)
    R0 = root_frames(root_tangents) if frames is None else np.asarray(frames, dtype=np.float64).reshape(S, 3, 3)
    offsets = np.concatenate([[0], np.cumsum(n_elements)]).astype(np.int64)
    E = int(offsets[-1])
    phi = np.ascontiguousarray(phi, dtype=np.float64).reshape(E, 3)
    lengths = np.ascontiguousarray(lengths, dtype=np.float64).reshape(E)
    padded, q = np.zeros((S, N)), np.zeros((S, N, 3))
    start, C, T, Omega = np.empty(E), np.empty((E, 3)), np.empty((E, 3)), np.empty((E, 3))
    roots = np.ascontiguousarray(np.asarray(root_positions, dtype=np.float64).reshape(S, 3))
    _assemble_kernel(np.ascontiguousarray(R0), roots, phi, lengths, n_elements, padded, q, start, C, T, Omega)
    helix = SuperHelix(root_positions, R0, padded, q, n_elements)
    table = CurveTable(elem_offsets=offsets, start=start, length=lengths, C=C, T=T, Omega=Omega,
                       strand_length=helix.strand_lengths)
    return helix, table


@njit(cache=True, error_model="numpy")
def _assemble_kernel(R0, roots, phi, lengths, n_elements, padded, q, start, C, T, Omega):
    """Frames, curvatures q (S, N, 3), padded lengths (S, N) and the flat table rows (start, C, T, Omega)
    of :func:`assemble_flat`.

    R = (r_ab) in scalars; R <- exp([Phi]x) R with the products summed as fma(Q_b2, r_2a, fma(Q_b1, r_1a,
    Q_b0 r_0a)), the rounding of numpy's matmul (OpenBLAS).
    """
    k = 0
    for s in range(R0.shape[0]):
        r00, r01, r02 = R0[s, 0, 0], R0[s, 0, 1], R0[s, 0, 2]
        r10, r11, r12 = R0[s, 1, 0], R0[s, 1, 1], R0[s, 1, 2]
        r20, r21, r22 = R0[s, 2, 0], R0[s, 2, 1], R0[s, 2, 2]
        acc_s, a0, a1, a2 = 0.0, 0.0, 0.0, 0.0
        for j in range(n_elements[s]):
            p0, p1, p2 = phi[k, 0], phi[k, 1], phi[k, 2]
            x = p0 * p0 + p1 * p1 + p2 * p2
            f1, f2, f3 = f123_s(x)
            l = lengths[k]
            padded[s, j] = l
            safe_l = l if l > 0 else 1.0
            # q = R^T Phi / l, Omega = Phi / l
            if l <= 0:
                q[s, j, 0], q[s, j, 1], q[s, j, 2] = 0.0, 0.0, 0.0
            else:
                q[s, j, 0] = (r00 * p0 + r10 * p1 + r20 * p2) / safe_l
                q[s, j, 1] = (r01 * p0 + r11 * p1 + r21 * p2) / safe_l
                q[s, j, 2] = (r02 * p0 + r12 * p1 + r22 * p2) / safe_l
            Omega[k, 0], Omega[k, 1], Omega[k, 2] = p0 / safe_l, p1 / safe_l, p2 / safe_l
            # the node and its tangent (first column of R); the chord l (t + f2 Phi x t + f3 Phi x (Phi x t))
            T[k, 0], T[k, 1], T[k, 2] = r00, r10, r20
            start[k] = acc_s
            acc_s += l
            C[k, 0], C[k, 1], C[k, 2] = a0 + roots[s, 0], a1 + roots[s, 1], a2 + roots[s, 2]
            u0, u1, u2 = p1 * r20 - p2 * r10, p2 * r00 - p0 * r20, p0 * r10 - p1 * r00
            v0, v1, v2 = p1 * u2 - p2 * u1, p2 * u0 - p0 * u2, p0 * u1 - p1 * u0
            a0 += l * (r00 + f2 * u0 + f3 * v0)
            a1 += l * (r10 + f2 * u1 + f3 * v1)
            a2 += l * (r20 + f2 * u2 + f3 * v2)
            # R <- exp([Phi]x) R, exp([Phi]x) = I + f1 [Phi]x + f2 [Phi]x^2 (as the reference's rotation_matrices)
            q00 = 1.0 + f2 * (p0 * p0 - x)
            q11 = 1.0 + f2 * (p1 * p1 - x)
            q22 = 1.0 + f2 * (p2 * p2 - x)
            q01 = -f1 * p2 + f2 * p0 * p1
            q10 = f1 * p2 + f2 * p0 * p1
            q02 = f1 * p1 + f2 * p0 * p2
            q20 = -f1 * p1 + f2 * p0 * p2
            q12 = -f1 * p0 + f2 * p1 * p2
            q21 = f1 * p0 + f2 * p1 * p2
            r00, r10, r20 = (fma(q02, r20, fma(q01, r10, q00 * r00)), fma(q12, r20, fma(q11, r10, q10 * r00)),
                             fma(q22, r20, fma(q21, r10, q20 * r00)))
            r01, r11, r21 = (fma(q02, r21, fma(q01, r11, q00 * r01)), fma(q12, r21, fma(q11, r11, q10 * r01)),
                             fma(q22, r21, fma(q21, r11, q20 * r01)))
            r02, r12, r22 = (fma(q02, r22, fma(q01, r12, q00 * r02)), fma(q12, r22, fma(q11, r12, q10 * r02)),
                             fma(q22, r22, fma(q21, r12, q20 * r02)))
            k += 1


