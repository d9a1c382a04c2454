"""Head motion for the simulator: the rigid transform of the head and of the roots at time t.

``head_motion(t) -> (R, T)`` maps the initial pose to the pose at t (x_world = R x_rest + T); its
velocity and acceleration come from central differences.  A static head is ``head_motion = None``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np


def rigid_motion(head_motion: Callable, t: float, eps: float = 1e-4):
    """Transform (R, T) of the head at t, its velocity (V, Omega) and acceleration (a, alpha) by
    central differences; x_world = R x_rest + T, v(x) = V + Omega x (x - T)."""
    R, T = (np.asarray(a, dtype=np.float64) for a in head_motion(t))
    Rm, Tm = (np.asarray(a, dtype=np.float64) for a in head_motion(t - eps))
    Rp, Tp = (np.asarray(a, dtype=np.float64) for a in head_motion(t + eps))
    V = (Tp - Tm) / (2 * eps)
    acc = (Tp - 2 * T + Tm) / eps**2

    def axial(S):
        return 0.5 * np.array([S[2, 1] - S[1, 2], S[0, 2] - S[2, 0], S[1, 0] - S[0, 1]])

    Om = axial((Rp - Rm) / (2 * eps) @ R.T)
    Om_p = axial((Rp - R) / eps @ R.T)
    Om_m = axial((R - Rm) / eps @ Rm.T)
    alpha = (Om_p - Om_m) / eps
    return R, T, V, Om, acc, alpha


@dataclass
class RootPose:
    """Roots (S, 3) and root frames (S, 3, 3) at one time; for a moving head also its transform
    (R, T), velocity (V, Omega) and the root motion of dynamics.inertia_terms (``root_motion``)."""

    roots: np.ndarray
    frames: np.ndarray
    R: np.ndarray | None = None
    T: np.ndarray | None = None
    V: np.ndarray | None = None
    Omega: np.ndarray | None = None
    root_motion: dict | None = None

    @property
    def moving(self) -> bool:
        return self.R is not None


class HeadMotion:
    """Where the head puts the roots at time t (static when ``head_motion`` is None)."""

    def __init__(self, roots: np.ndarray, frames: np.ndarray, head_motion: Callable | None = None):
        self.base_roots = np.asarray(roots, dtype=np.float64).copy()
        self.base_frames = np.asarray(frames, dtype=np.float64).copy()
        self.head_motion = head_motion

    @property
    def moving(self) -> bool:
        return self.head_motion is not None

    def transform(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        """(R, T) of the head at t, None for a static head."""
        if self.head_motion is None:
            return None
        R, T = (np.asarray(a, dtype=np.float64) for a in self.head_motion(t))
        return R, T

    def pose(self, t: float) -> RootPose:
        """Roots and frames at t; with a moving head the roots' velocity and acceleration too:
        v = V + Omega x (x - T),  a = acc + alpha x (x - T) + Omega x (Omega x (x - T))."""
        if self.head_motion is None:
            return RootPose(self.base_roots, self.base_frames)
        R, T, V, Om, acc, alpha = rigid_motion(self.head_motion, t)
        roots = self.base_roots @ R.T + T
        frames = R @ self.base_frames
        rel = roots - T
        motion = {"root_velocity": V + np.cross(Om, rel), "root_angular_velocity": np.broadcast_to(Om, rel.shape),
                  "root_acceleration": acc + np.cross(alpha, rel) + np.cross(Om, np.cross(Om, rel)),
                  "root_angular_acceleration": np.broadcast_to(alpha, rel.shape)}
        return RootPose(roots, frames, R, T, V, Om, motion)
