"""Stable inversion: per-strand stiffness factors that make the inverted groom a *stable* equilibrium.

The lecture's inverse problem asks for q0 *and* the material so that the groomed q is a stable
equilibrium.  A strand s whose bending and twisting stiffnesses (EI and GJ, i.e. E and G) are multiplied
by f_s has the stiffness ratio rho_s / f_s (stability.py: rho = lambda_max(K^-1/2 (dF/dq + dF_c/dq) K^-1/2)
on the motions its contacts allow, with the user's K), so it is stable iff f_s > rho_s.  The linear
density rho S is not changed: the strand keeps its weight and its inertia.

Policy (``groom invert --stabilize stiffness``, the default):

    f_s <- min(cap, margin * rho_s)   for every strand with rho_s >= f_s (unstable with its current f_s),

(a strand raised before: the growth of its rho with f extrapolated, ``stiffening_step``); other strands keep
f_s (1 at the start: only the strands that need it are stiffened).  The inversion is
then solved again with the new K (q0 and the contact forces depend on K, and so do the contacts that hold
a strand), and the ratios recomputed, until no strand needs more (or ``MAX_ROUNDS``).  Strands still
unstable at the cap are named in the report.
"""

from __future__ import annotations

import numpy as np

STABILIZE_MODES = ("none", "stiffness", "report")
DEFAULT_MARGIN = 1.1  # f_s = 1.1 rho_s: the weakest mode keeps ~10 % of its stiffness against gravity
DEFAULT_CAP = 100.0  # no strand is made more than 100x stiffer
MAX_ROUNDS = 8


#: the largest growth exponent k (rho ~ f^k) that stiffening_step extrapolates with
MAX_GROWTH = 0.5


def stiffening_step(ratio: np.ndarray, factor: np.ndarray, margin: float = DEFAULT_MARGIN,
                    cap: float = DEFAULT_CAP, previous: tuple | None = None) -> np.ndarray | None:
    """The next stiffness factors for the strands with rho >= f (unstable), never lower than now and at most
    ``cap``; None when nothing changes (all stable, or the unstable ones at the cap).

    A strand's rho is measured with the forces of the last solve, and stiffening a strand changes them: a stiffer
    strand takes more of the load, so its rho grows (measured on example_groom(1000): 33 of the 40 strands unstable
    after the first round had been raised in it, rho up 3-40 %).  Without ``previous`` every unstable strand gets
    margin * rho.  With ``previous`` = (ratio0, factor0), a strand's rho0 measured at f0 < f before its last raise,
    the growth rho ~ f^k, k = log(rho / rho0) / log(f / f0) clipped to [0, MAX_GROWTH], is extrapolated: the new f
    solves f = margin * rho (f / f_now)^k, i.e. f = (margin * rho * f_now^-k)^(1 / (1 - k)) (margin * rho when k =
    0), so that the strand is stable with the margin at the rho the new factor will bring, in one round instead of
    several."""
    ratio = np.asarray(ratio, dtype=np.float64)
    factor = np.asarray(factor, dtype=np.float64)
    need = ratio >= factor
    target = margin * ratio
    if previous is not None:
        ratio0, factor0 = (np.asarray(a, dtype=np.float64) for a in previous)
        known = need & (factor0 < factor) & (ratio0 > 0) & (ratio > ratio0)
        if np.any(known):
            k = np.clip(np.log(ratio[known] / ratio0[known]) / np.log(factor[known] / factor0[known]), 0.0, MAX_GROWTH)
            target[known] = (target[known] * factor[known] ** -k) ** (1.0 / (1.0 - k))
    new = factor.copy()
    new[need] = np.clip(target[need], factor[need], cap)
    if np.array_equal(new, factor):
        return None
    return new


def stabilization_report(mode: str, ratio: np.ndarray, factor: np.ndarray, kind: np.ndarray | None, rounds: int,
                         margin: float, cap: float, listed: int = 100) -> dict:
    """report.json's ``stability.stabilization``: what was stiffened, by how much, and what is still unstable.

    ``ratio``: rho per strand with the user's stiffness (the contacts of the last solve); ``factor``: the
    stiffness factors applied; a strand is stable iff rho < factor."""
    ratio = np.asarray(ratio, dtype=np.float64)
    factor = np.asarray(factor, dtype=np.float64)
    stiffened = np.flatnonzero(factor > 1.0)
    unstable = np.flatnonzero(ratio >= factor)
    out = {
        "mode": mode,
        "margin": margin,
        "max_factor_allowed": cap,
        "rounds": int(rounds),
        "stiffened_strands": int(len(stiffened)),
        "max_stiffness_factor": float(factor.max()) if len(factor) else 1.0,
        "median_stiffness_factor_of_stiffened": float(np.median(factor[stiffened])) if len(stiffened) else 1.0,
        "max_certified_factor": float(max(1.0, ratio.max())) if len(ratio) else 1.0,
        "stiffened_strand_ids": stiffened[:listed].tolist(),
        "unstable_strands": int(len(unstable)),
        "unstable_strand_ids": unstable[:listed].tolist(),
    }
    if kind is not None:
        out["strands_held_by_contacts"] = int(np.count_nonzero(np.asarray(kind) == 1))
    if mode == "stiffness" and len(unstable):
        out["note"] = (f"{len(unstable)} strand(s) need more than {cap:g}x their stiffness (or more rounds) "
                       "to be stable: they will move in a simulation")
    return out
