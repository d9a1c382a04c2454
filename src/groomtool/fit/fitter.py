"""Floating tangents: polylines -> G1 piecewise helices (Super-Helix state), with adaptive N.

Pipeline per strand with N elements (docs/maths.md section 4): N+1 samples Q_i evenly spaced in arc length
with tangents t_i (:mod:`.sampling`), closest co-helical points P_i (:mod:`.cohelicity`), the helix
through each pair (:mod:`.helix`), the frames and curvatures (:mod:`.state`).  :func:`fit_groom`
chooses N per strand: start at L / initial_spacing elements, measure the distance from every input
vertex to the fitted curve (:mod:`.error`) and grow N on the strands above tolerance, refitting only
those, until all pass or N reaches ``max_elements``.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from ..groom import Groom, GroomError
from ..rods.superhelix import SuperHelix
from ..timing import progress as progress_bar
from .cohelicity import constraint_residuals, relax_points
from .error import strand_errors
from .helix import helix_residuals, solve_chain, solve_helix
from .sampling import PolylineCurves, drop_repeated_vertices, ensure_four_vertices, vertex_arc_lengths
from .state import CurveTable, assemble_flat

DEFAULT_TOLERANCE_M = 5e-4  #: the fit tolerance when none is given (m): the inversion's and the CLI's default too

_clock = time.perf_counter  # stage timings (wall clock); the bench may swap in time.process_time
GROWTH_MIN, GROWTH_MAX = 1.2, 2.0   # bounds on the factor N grows by between passes


# --------------------------------------------------------------------------- results
@dataclass
class FixedFit:
    """A fit with given element boundaries.

    helix: the SuperHelix; samples, tangents (S, N+1, 3): its input; points (S, N+1, 3): after
    co-helicity relaxation (the fitted curve's nodes); phi (S, N, 3) world rotation per element;
    kind (S, N) helix case (see :class:`~groomtool.fit.helix.HelixSolution`); cohelicity (S, N),
    tangent_residual (S, N), chord_residual (S, N): the constraint and helix-solve residuals;
    length_error (S, N): fitted element length minus the given arc-length spacing (zeros if none given).
    """

    helix: SuperHelix
    samples: np.ndarray
    tangents: np.ndarray
    points: np.ndarray
    phi: np.ndarray
    kind: np.ndarray
    cohelicity: np.ndarray
    tangent_residual: np.ndarray
    chord_residual: np.ndarray
    length_error: np.ndarray
    table: CurveTable = field(repr=False, default=None)


@dataclass
class FitResult:
    """Result of :func:`fit_groom`, per strand (S,) unless said otherwise.

    helix: SuperHelix (n_elements per strand); max_error, mean_error: distance (m) from the input
    vertices to the fitted curve; tolerance: the effective tolerance; converged: max_error <= tolerance;
    strand_lengths: polyline lengths; passes: refinement passes run; timings: seconds per stage;
    settings: the arguments of the fit.
    """

    helix: SuperHelix
    max_error: np.ndarray
    mean_error: np.ndarray
    converged: np.ndarray
    tolerance: np.ndarray
    strand_lengths: np.ndarray
    passes: int = 0
    timings: dict = field(default_factory=dict)
    settings: dict = field(default_factory=dict)

    @property
    def n_elements(self) -> np.ndarray:
        return self.helix.n_elements

    @property
    def relative_max_error(self) -> np.ndarray:
        return self.max_error / np.maximum(self.strand_lengths, 1e-300)

    @property
    def failed(self) -> np.ndarray:
        """Ids of the strands whose error stayed above tolerance at max_elements."""
        return np.nonzero(~self.converged)[0]

    def summary(self) -> dict:
        return {
            "strands": int(len(self.max_error)),
            "elements": int(self.helix.n_elements.sum()),
            "elements_per_strand": {"min": int(self.helix.n_elements.min()), "mean": float(self.helix.n_elements.mean()),
                                    "max": int(self.helix.n_elements.max())},
            "max_error_m": float(self.max_error.max()),
            "mean_error_m": float(self.mean_error.mean()),
            "max_relative_error": float(self.relative_max_error.max()),
            "not_converged": int((~self.converged).sum()),
            "passes": self.passes,
            "timings_s": dict(self.timings),
        }


# --------------------------------------------------------------------------- core
def _fit_samples(Q, T, n_elements, relax=True, chord_tolerance=None, timings=None, frames=None):
    """Relax, solve the helices, assemble: padded samples (S, N+1, 3) -> (helix, table, P, sol, mask).

    chord_tolerance None: every helix exact through the relaxed points (a flat batch over elements);
    else (S,) metres: planar arcs where within that chord error, with error feedback
    (:func:`~groomtool.fit.helix.solve_chain`).
    """
    timings = timings if timings is not None else {}
    N = Q.shape[1] - 1
    t = _clock()
    P = relax_points(Q, T, n_elements) if relax else Q.copy()
    t1 = _clock()
    timings["relax"] = timings.get("relax", 0.0) + t1 - t
    mask = np.arange(N)[None, :] < n_elements[:, None]
    if chord_tolerance is None:
        sol = solve_helix(T[:, :-1][mask], T[:, 1:][mask], (P[:, 1:] - P[:, :-1])[mask])
    else:
        sol = solve_chain(P, T, n_elements, chord_tolerance)
    t2 = _clock()
    timings["helix"] = timings.get("helix", 0.0) + t2 - t1
    helix, table = assemble_flat(P[:, 0], T[:, 0], sol.phi, sol.length, n_elements, N, frames)
    timings["assemble"] = timings.get("assemble", 0.0) + _clock() - t2
    return helix, table, P, sol, mask


def fit_polyline_fixed(points_or_samples, tangents=None, arc_lengths=None, n_elements=None,
                       relax: bool = True, chord_tolerance=None, root_frames=None) -> FixedFit:
    """Fit with given element boundaries.

    - ``tangents`` given: ``points_or_samples`` are the element boundaries Q_i, (N+1, 3) or padded
      (S, N+1, 3), with their tangents (same shape); ``arc_lengths`` (same leading shape), optional,
      only feeds ``length_error``.
    - ``tangents`` None: ``points_or_samples`` is one polyline (V, 3) and ``arc_lengths`` (N+1,) the
      arc lengths (from its root, increasing) of the boundaries; points and tangents come from the
      local cubic of :mod:`.sampling`.

    ``n_elements`` (S,): elements per strand of padded input (default: all).  ``relax=False`` skips
    the co-helicity relaxation (the samples must be co-helical already, e.g. exact helix nodes).
    ``chord_tolerance`` (metres, scalar or (S,)): planar arcs (no twist) where they miss the chord by
    less than that, with error feedback (default: exact helices).  ``root_frames`` (S, 3, 3) or (3, 3): the root material
    frames (first column = the root tangent; default: :func:`~groomtool.fit.state.root_frames`).
    """
    X = np.asarray(points_or_samples, dtype=np.float64)
    given_s = None
    if tangents is None:
        if arc_lengths is None or X.ndim != 2:
            raise ValueError("without tangents, pass one polyline (V, 3) and the boundary arc lengths (N+1,)")
        s = np.asarray(arc_lengths, dtype=np.float64).ravel()
        pts, off, _ = drop_repeated_vertices(X, np.array([0, len(X)]))
        pts, off = ensure_four_vertices(pts, off)
        curves = PolylineCurves(pts, off)
        Q, T = curves.evaluate(np.zeros(len(s), dtype=np.int64), s)
        Q, T, given_s = Q[None], T[None], s[None]
        single = True
    else:
        T = np.asarray(tangents, dtype=np.float64)
        single = X.ndim == 2
        Q = X[None] if single else X
        T = T[None] if single else T
        T = T / np.linalg.norm(T, axis=-1, keepdims=True)
        if arc_lengths is not None:
            given_s = np.asarray(arc_lengths, dtype=np.float64).reshape(Q.shape[:2])
    S, N1, _ = Q.shape
    n = np.full(S, N1 - 1, dtype=np.int64) if n_elements is None else np.asarray(n_elements, dtype=np.int64).ravel()
    frames = None if root_frames is None else np.asarray(root_frames, dtype=np.float64).reshape(S, 3, 3)
    tol = None if chord_tolerance is None else np.broadcast_to(np.asarray(chord_tolerance, dtype=np.float64), (S,))
    helix, table, P, sol, mask = _fit_samples(Q, T, n, relax=relax, chord_tolerance=tol, frames=frames)
    N = N1 - 1
    co = constraint_residuals(P, T, n)
    rt, rc = helix_residuals(sol.phi, sol.length, T[:, :-1][mask], T[:, 1:][mask], (P[:, 1:] - P[:, :-1])[mask])
    tang, chrd, kind = np.zeros((S, N)), np.zeros((S, N)), np.zeros((S, N), dtype=np.int64)
    tang[mask], chrd[mask], kind[mask] = rt, rc, sol.kind
    phi = np.zeros((S, N, 3))
    phi[mask] = sol.phi
    lerr = np.zeros((S, N))
    if given_s is not None:
        lerr = np.where(mask, helix.lengths - np.diff(given_s, axis=1), 0.0)
    out = FixedFit(helix, Q, T, P, phi, kind, co, tang, chrd, lerr, table)
    if single:
        for name in ("samples", "tangents", "points", "phi", "kind", "cohelicity", "tangent_residual",
                     "chord_residual", "length_error"):
            setattr(out, name, getattr(out, name)[0])
    return out


def effective_tolerance(strand_lengths, tolerance=DEFAULT_TOLERANCE_M, relative_tolerance=None) -> np.ndarray:
    """Per-strand tolerance (m): min(tolerance, relative_tolerance * L) when both are given."""
    L = np.asarray(strand_lengths, dtype=np.float64)
    if tolerance is None and relative_tolerance is None:
        raise ValueError("give tolerance, relative_tolerance or both")
    tol = np.full(L.shape, np.inf)
    if tolerance is not None:
        tol = np.minimum(tol, float(tolerance))
    if relative_tolerance is not None:
        tol = np.minimum(tol, float(relative_tolerance) * L)
    return tol


def fit_groom(groom: Groom, tolerance: float | None = DEFAULT_TOLERANCE_M, relative_tolerance: float | None = None,
              max_elements: int = 256, initial_spacing: float = 0.02, min_elements: int = 2,
              twist_budget: float = 0.25, progress: bool = False) -> FitResult:
    """Fit every strand of ``groom`` with a Super-Helix within tolerance, choosing N per strand.

    tolerance (m) and relative_tolerance (fraction of the strand length): the effective tolerance is
    the smaller of the two when both are given.  N starts at ceil(L / initial_spacing) (at least
    ``min_elements``) and grows on the strands above tolerance by the factor the error predicts
    (error ~ N^-p, p measured per strand; between 1.2x and 2x), capped at ``max_elements``; strands still above tolerance
    there are reported (``converged`` False, a warning), never dropped.

    twist_budget: an element whose planar arc (zero twist) misses its chord direction by at most
    twist_budget * tolerance takes it (with error feedback, so the deviations do not add up); the
    others stay exact helices.  0 makes every helix pass exactly through the relaxed points (the twist
    then follows the data's torsion, noise included).
    """
    timings = {"sample": 0.0, "relax": 0.0, "helix": 0.0, "assemble": 0.0, "error": 0.0}
    t_start = _clock()
    points, offsets, _ = drop_repeated_vertices(groom.points, groom.offsets)
    counts = np.diff(offsets)
    if np.any(counts < 2):
        bad = np.nonzero(counts < 2)[0]
        raise GroomError(f"{groom.source}: {len(bad)} strand(s) have fewer than 2 distinct vertices "
                         f"(first: strand {bad[0]}); remove them before fitting")
    points, offsets = ensure_four_vertices(points, offsets)
    curves = PolylineCurves(points, offsets)
    L = curves.lengths
    S = len(L)
    tol = effective_tolerance(L, tolerance, relative_tolerance)
    n_now = np.clip(np.ceil(L / initial_spacing).astype(np.int64), min_elements, max_elements)

    # input vertices, as given (measured against the fit): strand, arc-length fraction
    vpoints = groom.points
    vstrand = groom.strand_index
    varc, vlen = vertex_arc_lengths(groom.points, groom.offsets)
    vfrac = varc / np.maximum(vlen[vstrand], 1e-300)

    max_err = np.zeros(S)
    mean_err = np.zeros(S)
    final_pass = np.full(S, -1)
    prev_n, prev_err = np.zeros(S, dtype=np.int64), np.zeros(S)
    passes = []
    active = np.arange(S)
    bar = None
    if progress:
        bar = progress_bar(S, "fit", quiet=False, unit="strand")
    timings["prepare"] = _clock() - t_start
    while len(active):
        p = len(passes)
        n_act = n_now[active]
        N = int(n_act.max())
        t = _clock()
        # samples s_i = L i / n (padding repeats the tip)
        i = np.minimum(np.arange(N + 1)[None, :], n_act[:, None])
        s = L[active, None] * i / n_act[:, None]
        strand_rep = np.repeat(active, N + 1)
        Q, T = curves.evaluate(strand_rep, s.ravel())
        Q, T = Q.reshape(len(active), N + 1, 3), T.reshape(len(active), N + 1, 3)
        timings["sample"] += _clock() - t
        budget = twist_budget * tol[active] if twist_budget > 0 else None
        helix, table, _, _, _ = _fit_samples(Q, T, n_act, chord_tolerance=budget, timings=timings)
        t = _clock()
        at_cap = n_act >= max_elements
        mx, mn = strand_errors(table, groom.offsets, vpoints, vfrac, active, n_act, tol[active], at_cap)
        timings["error"] += _clock() - t
        max_err[active], mean_err[active] = mx, mn
        done = (mx <= tol[active]) | at_cap
        final_pass[active[done]] = p
        passes.append((active, helix))
        if bar is not None:
            bar.update(int(done.sum()))
        # next N: error ~ N^-p, p measured from the strand's last two passes (1.5 before that),
        # predicts the factor (err / tol)^(1/p); 10 % margin, between GROWTH_MIN and GROWTH_MAX
        nd = active[~done]
        order = np.full(len(nd), 1.5)
        seen = prev_n[nd] > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            measured = np.log(prev_err[nd] / mx[~done]) / np.log(n_act[~done] / prev_n[nd])
        order[seen] = np.clip(np.nan_to_num(measured[seen], nan=1.0), 0.75, 3.0)
        grow = np.clip(1.1 * (mx[~done] / tol[nd]) ** (1.0 / order), GROWTH_MIN, GROWTH_MAX)
        prev_n[nd], prev_err[nd] = n_act[~done], mx[~done]
        n_now[nd] = np.minimum(np.ceil(n_act[~done] * grow).astype(np.int64), max_elements)
        active = active[~done]
    if bar is not None:
        bar.close()

    t = _clock()
    helix = _merge(passes, final_pass, S)
    timings["merge"] = _clock() - t
    converged = max_err <= tol
    if not converged.all():
        bad = np.nonzero(~converged)[0]
        warnings.warn(f"{groom.source}: {len(bad)} strand(s) above tolerance at max_elements={max_elements} "
                      f"(worst {max_err[bad].max():.3g} m, strand {bad[np.argmax(max_err[bad])]})", stacklevel=2)
    timings["total"] = _clock() - t_start
    settings = {"tolerance": tolerance, "relative_tolerance": relative_tolerance, "max_elements": max_elements,
                "initial_spacing": initial_spacing, "min_elements": min_elements, "twist_budget": twist_budget}
    return FitResult(helix, max_err, mean_err, converged, tol, L, len(passes), timings, settings)


def _merge(passes, final_pass, S) -> SuperHelix:
    """One SuperHelix from the passes, each strand taken from its final pass."""
    N = max((int(h.n_elements[final_pass[ids] == p].max(initial=0)) for p, (ids, h) in enumerate(passes)),
            default=0)
    roots, frames = np.zeros((S, 3)), np.zeros((S, 3, 3))
    lengths, curv = np.zeros((S, N)), np.zeros((S, N, 3))
    n_el = np.zeros(S, dtype=np.int64)
    for p, (ids, h) in enumerate(passes):
        sel = final_pass[ids] == p
        dst = ids[sel]
        k = min(N, h.max_elements)
        roots[dst], frames[dst], n_el[dst] = h.root_positions[sel], h.root_frames[sel], h.n_elements[sel]
        lengths[dst, :k] = h.lengths[sel, :k]
        curv[dst, :k] = h.curvatures[sel, :k]
    return SuperHelix(roots, frames, lengths, curv, n_el)
