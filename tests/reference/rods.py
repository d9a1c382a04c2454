"""References and helpers for groomtool.rods that only the tests use.

* :func:`clothoid_gravity_force_jacobian_full`: ``rods.clothoid.gravity_force_jacobian`` by the complex
  step with every element recomputed per column (the fast one recomputes only a node's two elements).
* :func:`transport`, :func:`rotate_about`: frames moved along a discrete rod (tests of the DER rest data).
"""

from __future__ import annotations

import numpy as np

from groomtool.rods import clothoid as cl
from groomtool.rods import discrete as dr


def clothoid_gravity_force_jacobian_full(clothoid: cl.SuperClothoid, linear_density: float, gravity,
                                          chunk: int = 1024):
    """The complex step with every element recomputed per column (reference for the tests)."""
    S, N = clothoid.lengths.shape
    n = 3 * (N + 1)
    out = np.zeros((S, n, n))
    sid_all, col_all = np.nonzero(np.arange(n)[None, :] // 3 <= clothoid.n_elements[:, None])
    for start in range(0, len(sid_all), chunk):
        sid = sid_all[start:start + chunk]
        col = col_all[start:start + chunk]
        q = clothoid.curvatures[sid].astype(np.complex128).reshape(len(sid), n)
        q[np.arange(len(sid)), col] += 1j * cl.COMPLEX_STEP
        sub = cl.SuperClothoid(clothoid.root_positions[sid], clothoid.root_frames[sid], clothoid.lengths[sid],
                               q.reshape(len(sid), N + 1, 3), clothoid.n_elements[sid])
        F = cl.gravity_force(sub, linear_density, gravity)
        out[sid, :, col] = F.reshape(len(sid), n).imag / cl.COMPLEX_STEP
    return out


def transport(v: np.ndarray, t_old: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Parallel transport of vectors v (N, 3) from unit tangents t_old to t_new (the minimal rotation):
    P v = c v + b x v + b (b . v) / (1 + c), b = t_old x t_new, c = t_old . t_new."""
    b = dr.cross(t_old, t_new)
    c = dr.dot(t_old, t_new)
    return c[:, None] * v + dr.cross(b, v) + b * (dr.dot(b, v) / (1.0 + c))[:, None]


def rotate_about(v: np.ndarray, axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate v (N, 3), normal to the unit ``axis`` (N, 3), by ``angle`` (N,): v cos + (axis x v) sin."""
    return np.cos(angle)[:, None] * v + np.sin(angle)[:, None] * dr.cross(axis, v)

