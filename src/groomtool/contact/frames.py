"""Orthonormal contact frames (e_N, e_T1, e_T2) built from contact normals.

Rule: e_T1 is the strand tangent projected onto the contact's tangent plane (the plane orthogonal to
e_N), normalised; friction is then split into "along the strand" (T1) and "across it" (T2).  When no
tangent is given, or it is (nearly) parallel to the normal, e_T1 comes from the coordinate axis least
aligned with e_N (lowest index on ties), projected on the tangent plane.  e_T2 = e_N x e_T1, so the rows
(e_N, e_T1, e_T2) form a right-handed orthonormal basis.  Both rules are deterministic; the
tangent rule is continuous in the geometry wherever the tangent is not parallel to the normal.
"""

from __future__ import annotations

import numpy as np

#: below this |sin(angle)| between tangent and normal the tangent is not used
PARALLEL_SIN = 1e-6


def _least_aligned_axis(normals: np.ndarray) -> np.ndarray:
    """Unit coordinate axis least aligned with each normal, (m, 3)."""
    axis = np.argmin(np.abs(normals), axis=1)
    return np.eye(3)[axis]


def _project_unit(vectors: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project on the plane orthogonal to ``normals``; return the unit result and its norm before."""
    proj = vectors - np.sum(vectors * normals, axis=1, keepdims=True) * normals
    norm = np.linalg.norm(proj, axis=1)
    safe = np.where(norm > 0.0, norm, 1.0)
    return proj / safe[:, None], norm


def contact_frames(normals: np.ndarray, tangents: np.ndarray | None = None) -> np.ndarray:
    """Frames (m, 3, 3) with rows (e_N, e_T1, e_T2) for unit-ish ``normals`` (m, 3).

    ``tangents`` (m, 3), optional: the strand direction at each contact; e_T1 follows it (see the module
    docstring).  Normals are renormalised; a zero normal is an error.
    """
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    length = np.linalg.norm(n, axis=1)
    if np.any(~(length > 0.0)):
        raise ValueError("contact_frames: every normal must be non-zero and finite")
    n = n / length[:, None]

    t1, norm = _project_unit(_least_aligned_axis(n), n)
    if tangents is not None:
        tan = np.asarray(tangents, dtype=np.float64).reshape(-1, 3)
        if tan.shape != n.shape:
            raise ValueError(f"contact_frames: tangents shape {tan.shape} != normals shape {n.shape}")
        tan_len = np.linalg.norm(tan, axis=1)
        t_proj, t_norm = _project_unit(tan, n)
        use = t_norm > PARALLEL_SIN * np.where(tan_len > 0.0, tan_len, np.inf)
        t1 = np.where(use[:, None], t_proj, t1)
    t2 = np.cross(n, t1)
    t2 /= np.linalg.norm(t2, axis=1, keepdims=True)
    t1 = np.cross(t2, n)  # re-orthogonalise to machine precision
    return np.stack([n, t1, t2], axis=1)
