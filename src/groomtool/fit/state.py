"""From per-element world rotations to the Super-Helix state (MATH.md section 3.4).

Root frame R_0 = (n0, n1, n2) with n0 = t_0 and n1 the component orthogonal to t_0 of the world axis
least aligned with t_0, normalised; n2 = n0 x n1.  Then along the strand

    R_{j+1} = exp([Phi_j]x) R_j  (= R_j exp(l_j [omega_j]x)),    omega_j = q_j = R_j^T Phi_j / l_j,

so the frame is continuous at every joint and the curve is G1 by construction.  Node positions use
the same closed form as :mod:`groomtool.rods.superhelix`:

    C_{j+1} = C_j + l_j (I + f2 [Phi_j]x + f3 [Phi_j]x^2) t_j,     f_n = f_n(|Phi_j|^2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..rods.superhelix import SuperHelix, kinematics
from .kernels import cross, dot, f123


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


def rotation_matrices(phi) -> np.ndarray:
    """exp([Phi]x) = I + f1 [Phi]x + f2 [Phi]x^2 for phi (..., 3) -> (..., 3, 3)."""
    phi = np.asarray(phi, dtype=np.float64)
    x = dot(phi, phi)
    a, b, _ = f123(x)
    out = np.empty(phi.shape[:-1] + (3, 3))
    px, py, pz = phi[..., 0], phi[..., 1], phi[..., 2]
    out[..., 0, 0] = 1.0 + b * (px * px - x)
    out[..., 1, 1] = 1.0 + b * (py * py - x)
    out[..., 2, 2] = 1.0 + b * (pz * pz - x)
    out[..., 0, 1] = -a * pz + b * px * py
    out[..., 1, 0] = a * pz + b * px * py
    out[..., 0, 2] = a * py + b * px * pz
    out[..., 2, 0] = -a * py + b * px * pz
    out[..., 1, 2] = -a * px + b * py * pz
    out[..., 2, 1] = a * px + b * py * pz
    return out


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
    phi = np.asarray(phi, dtype=np.float64)
    lengths = np.asarray(lengths, dtype=np.float64)
    n_elements = np.asarray(n_elements, dtype=np.int64)
    S, N = lengths.shape
    R0 = root_frames(root_tangents) if frames is None else np.asarray(frames, dtype=np.float64).reshape(S, 3, 3)
    Q = rotation_matrices(phi)                                     # (S, N, 3, 3)
    R = np.empty((S, N + 1, 3, 3))
    R[:, 0] = R0
    for j in range(N):
        R[:, j + 1] = Q[:, j] @ R[:, j]
    safe_l = np.where(lengths > 0, lengths, 1.0)
    q = np.einsum("snba,snb->sna", R[:, :-1], phi) / safe_l[..., None]
    q[lengths <= 0] = 0.0
    helix = SuperHelix(root_positions, R0, lengths, q, n_elements)
    return helix, _table(helix, R[:, :-1, :, 0], phi, safe_l)


def _table(helix: SuperHelix, T, phi, safe_l) -> CurveTable:
    """Node positions by C_{j+1} = C_j + l_j (t_j + f2 Phi x t_j + f3 Phi x (Phi x t_j))."""
    S, N = helix.lengths.shape
    _, f2, f3 = f123(dot(phi, phi))
    pt = cross(phi, T)
    chord = helix.lengths[..., None] * (T + f2[..., None] * pt + f3[..., None] * cross(phi, pt))
    C = np.empty((S, N + 1, 3))
    C[:, 0] = helix.root_positions
    np.cumsum(chord, axis=1, out=C[:, 1:])
    C[:, 1:] += helix.root_positions[:, None]
    mask = helix.element_mask
    starts = helix.element_starts[:, :-1]
    return CurveTable(
        elem_offsets=helix.flat_offsets(),
        start=starts[mask], length=helix.lengths[mask],
        C=C[:, :-1][mask], T=T[mask], Omega=(phi / safe_l[..., None])[mask],
        strand_length=helix.strand_lengths,
    )


def curve_table(helix: SuperHelix) -> CurveTable:
    """The :class:`CurveTable` of any SuperHelix (node frames from superhelix.kinematics)."""
    kin = kinematics(helix)
    mask = helix.element_mask
    R = kin.R[:, :-1]
    omega_world = np.einsum("snab,snb->sna", R, helix.curvatures)
    return CurveTable(
        elem_offsets=helix.flat_offsets(),
        start=helix.element_starts[:, :-1][mask], length=helix.lengths[mask],
        C=kin.C[:, :-1][mask], T=R[..., 0][mask], Omega=omega_world[mask],
        strand_length=helix.strand_lengths,
    )
