"""The whole inversion (``groom invert``): fit, contacts, the inverse problem with stabilisation, discrete
rest data, the equilibrium check and the report; :func:`invert_groom` returns an :class:`InversionResult`.

The inverse problem itself (K, F, the SOCQP, its solve, q0, the equilibrium residuals) is
inverse_problem.py; which solver runs is solver_choice.py; the stability criteria are stability.py and
the stiffening rule stabilize.py.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from .fit import fit_groom
from .fit.fitter import DEFAULT_TOLERANCE_M
from .groom import Groom, GroomError
from .inverse_problem import (MODELS, admm_geometry, build_inverse_problem, cone_violation, equilibrium_residuals,
                              isolated_rest_curvatures, model_name, rest_curvatures_with_contacts, rod_module,
                              solve_inverse_problem, solver_method, strand_stiffness)
from .deprecation import rename_field
from .material import Material
from .rods import superhelix as sh
from .rods.cosserat import cosserat_rest_data
from .rods.der import der_rest_data
from .rods.discrete import RestDataError, prepare_rods, strand_stiffness_factors
from .solver_choice import AUTO_GS_MAX_REDUNDANT, Q0_TOLERANCE, redundant_strand_fraction
from .stability import HeldStability, held_stiffness_ratios, stiffness_ratios
from .stabilize import DEFAULT_CAP, DEFAULT_MARGIN, MAX_ROUNDS, STABILIZE_MODES, stabilization_report, stiffening_step
from .timing import Timer, progress

GUESSES = ("current", "tip")
SOLVERS = ("auto", "gs", "clarabel", "admm")  # the contact solve (solver_choice.py; admm: solvers/admm.py)
CONTACT_MODES = ("none", "head", "all")


class FeasibleSolveWarning(RuntimeWarning):
    """The contact solve stopped before its tolerance with feasible forces, which were kept (report:
    solve.status "feasible", its residual and q0_error_bound)."""


class SolverFailure(RuntimeError):
    """The contact solver did not reach its tolerance: carries the status, the residual and the report
    up to the solve (fit, contacts, solve details, timings_s of the stages run)."""

    def __init__(self, message: str, status: str, residual: float, report: dict | None = None):
        super().__init__(message)
        self.status = status
        self.residual = residual
        self.report = report or {}


@dataclass
class InversionParams:
    """Everything that decides the inversion besides the groom and the head."""

    material: Material = field(default_factory=Material)
    tolerance: float = DEFAULT_TOLERANCE_M
    relative_tolerance: float | None = None
    contacts: str = "none"  # none | head | all
    contact_radius: float | None = None
    wisp_radius: float | None = None  # each strand stands for a wisp of this radius (guide strands): see wisp_report
    guess: str = "current"  # current | tip
    gamma: float = 1e-4
    solver: str = "auto"  # auto | gs | clarabel | admm (SOLVERS)
    solver_tolerance: float = 1e-8
    max_sweeps: int = 5000  # the Gauss-Seidel sweep budget (--max-sweeps; clarabel keeps its own iteration limit)
    q0_tolerance: float | None = Q0_TOLERANCE  # stop once the certified relative rest-curvature error is below
    #                                            (None: off; docs/solvers.md section 11)
    strict: bool = False  # an unconverged solve raises SolverFailure instead of returning its feasible forces
    snap_roots: bool = False
    samples_per_element: int = 8
    rod_segments: int | None = None  # discrete rest data: None = the input's own vertices
    discrete_rest_data: bool = True
    stabilize: str = "stiffness"  # none | stiffness | report (stabilize.py)
    stability_margin: float = DEFAULT_MARGIN
    max_stiffness_factor: float = DEFAULT_CAP
    stiffness_factor: np.ndarray | None = None  # (S,) initial per-strand factors on E and G (None: all 1)
    friction_margin: float = 0.1  # the forces solved lie in the cones of (1 - margin) mu: they stick, with a margin
    model: str = "superhelix"  # superhelix | clothoid (Super Space Clothoids, docs/clothoid.md)

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"model must be one of {MODELS}, got {self.model!r}")
        if self.contacts not in CONTACT_MODES:
            raise ValueError(f"contacts must be one of {CONTACT_MODES}, got {self.contacts!r}")
        if self.guess not in GUESSES:
            raise ValueError(f"guess must be one of {GUESSES}, got {self.guess!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {SOLVERS}, got {self.solver!r}")
        if not (self.gamma >= 0):
            raise ValueError(f"gamma must be >= 0, got {self.gamma}")
        if not (self.tolerance > 0):
            raise ValueError(f"tolerance must be > 0, got {self.tolerance}")
        if self.rod_segments is not None and self.rod_segments < 2:
            raise ValueError(f"rod_segments must be >= 2, got {self.rod_segments}")
        if not (self.solver_tolerance > 0):
            raise ValueError(f"solver_tolerance must be > 0, got {self.solver_tolerance}")
        if self.max_sweeps < 1:
            raise ValueError(f"max_sweeps must be >= 1, got {self.max_sweeps}")
        if self.q0_tolerance is not None and not (self.q0_tolerance > 0):
            raise ValueError(f"q0_tolerance must be > 0 (or None), got {self.q0_tolerance}")
        if self.wisp_radius is not None:
            if not (self.wisp_radius >= self.material.radius and np.isfinite(self.wisp_radius)):
                raise ValueError(f"wisp radius must be at least the fibre radius {self.material.radius:g} m, "
                                 f"got {self.wisp_radius:g}")
            if self.contact_radius is not None:
                raise ValueError("give a wisp radius or a contact radius, not both "
                                 "(a wisp's contact radius is its radius)")
        if self.stabilize not in STABILIZE_MODES:
            raise ValueError(f"stabilize must be one of {STABILIZE_MODES}, got {self.stabilize!r}")
        if not (self.stability_margin >= 1.0 and np.isfinite(self.stability_margin)):
            raise ValueError(f"stability margin must be >= 1, got {self.stability_margin}")
        if not (0.0 <= self.friction_margin < 1.0):
            raise ValueError(f"friction margin must be in [0, 1), got {self.friction_margin}")
        if not (self.max_stiffness_factor >= 1.0 and np.isfinite(self.max_stiffness_factor)):
            raise ValueError(f"max stiffness factor must be >= 1, got {self.max_stiffness_factor}")


rename_field(InversionParams, "max_iterations", "max_sweeps")  # deprecated name (before issue 18)


# --------------------------------------------------------------------------- the whole job
@dataclass
class InversionResult:
    """What ``groom invert`` computes: the fitted Super-Helices, their rest curvatures, the contacts
    and forces, and the report (also written as report.json).  With ``model="clothoid"`` ``helix`` is a
    :class:`~groomtool.rods.clothoid.SuperClothoid` and the curvatures are nodal, (S, N + 1, 3)."""

    groom: Groom
    head: object
    params: InversionParams
    helix: sh.SuperHelix
    rest_curvatures: np.ndarray
    fit_max_error: np.ndarray
    fit_mean_error: np.ndarray
    gravity: np.ndarray
    contacts: object = None
    forces: np.ndarray = None  # (m, 3) in contact frames (N, T1, T2), newtons
    stiffness_ratio: np.ndarray = None  # isolated, with the input material (stability.stiffness_ratios)
    report: dict = field(default_factory=dict)
    extra_arrays: dict = field(default_factory=dict)  # more arrays for rest.npz (discrete rod data)
    stiffness_factor: np.ndarray = None  # (S,) E and G of strand s are f_s times the material's (stabilize.py)
    held_ratio: np.ndarray = None  # (S,) stiffness ratio with the contacts that hold the strand, input material

    def strand_young_modulus(self) -> np.ndarray:
        """(S,) Young's modulus of every strand (Pa): the material's times the stiffness factor."""
        return self.material.young_modulus * self._factor()

    def strand_shear_modulus(self) -> np.ndarray:
        """(S,) shear modulus of every strand (Pa)."""
        return self.material.G * self._factor()

    def _factor(self) -> np.ndarray:
        return np.ones(self.helix.n_strands) if self.stiffness_factor is None else np.asarray(self.stiffness_factor)

    def stiffness(self):
        """K (S, N, 3) with the per-strand moduli (clothoid: the banded (diagonal, off-diagonal) blocks)."""
        return strand_stiffness(self.helix, self.material, self._factor())

    @property
    def model(self) -> str:
        """"superhelix" or "clothoid"."""
        return model_name(self.helix)

    @property
    def material(self) -> Material:
        return self.params.material

    def rest_helix(self) -> sh.SuperHelix:
        """The strands with their rest curvatures: the shape they take with no gravity, no contact."""
        return self.helix.with_curvatures(self.rest_curvatures)

    def rest_shape(self, per_element: int = 8):
        """(points, offsets) of the rest shape sampled ``per_element`` times per element."""
        pts, offsets, _, _ = rod_module(self.helix).sample(self.rest_helix(), per_element)
        return pts, offsets

    def fitted_shape(self, per_element: int = 8):
        pts, offsets, _, _ = rod_module(self.helix).sample(self.helix, per_element)
        return pts, offsets

    def save(self, outdir, formats=("npz", "obj", "json")):
        from .io.results import write_result  # io (trimesh, 0.9 s): kept off the CLI's start

        return write_result(self, outdir, formats=formats)


def invert_groom(groom: Groom, head=None, params: InversionParams | None = None,
                 quiet: bool = True) -> InversionResult:
    """Fit, detect contacts, solve the inverse problem and check the equilibrium.

    When the contact solver stops before its tolerance with forces in their cones (any such forces make the
    groom an exact equilibrium), the result is kept with report solve.status "feasible", its residual and
    q0_error_bound, and a FeasibleSolveWarning; with ``params.strict`` (or non-finite forces) it raises
    SolverFailure instead (nothing is written then).
    """
    params = params or InversionParams()
    material = params.material
    gravity = groom.gravity(material.gravity)
    timer = Timer()
    report: dict = {"input": groom.source, "up": groom.up, "material": material.as_dict(),
                    "gravity_m_s2": gravity.tolist()}
    if "repairs" in groom.metadata:  # what load_groom(repair=True) dropped (input indices; rest.npz input_strand)
        report["repairs"] = dict(groom.metadata["repairs"])

    if params.snap_roots and head is not None:
        from .contact.head import snap_roots  # contact (0.3 s): kept off the CLI's start

        with timer.stage("snap_roots"):
            groom, gaps = _snap_groom_roots(groom, head, snap_roots)
        report["roots"] = {"mode": "snapped", **_gap_summary(gaps)}
    elif head is not None:
        from .contact.head import root_gaps  # kept off the CLI's start

        gaps = root_gaps(groom.points[groom.offsets[:-1]], head)
        report["roots"] = {"mode": "gap_reported", **_gap_summary(gaps)}

    report["model"] = params.model
    with timer.stage("fit"):
        if params.model == "clothoid":
            from .fit.clothoid_fit import fit_clothoid_groom

            fit = fit_clothoid_groom(groom, tolerance=params.tolerance, relative_tolerance=params.relative_tolerance,
                                     progress=not quiet)
        else:
            fit = fit_groom(groom, tolerance=params.tolerance, relative_tolerance=params.relative_tolerance,
                            progress=not quiet)
    helix = fit.helix
    mod = rod_module(helix)
    report["strands"] = int(helix.n_strands)
    report["elements"] = int(helix.n_elements.sum())
    report["fit"] = {"max_error_m": float(np.max(fit.max_error)) if len(fit.max_error) else 0.0,
                     "mean_error_m": float(np.mean(fit.mean_error)) if len(fit.mean_error) else 0.0,
                     "tolerance_m": params.tolerance,
                     "relative_tolerance": params.relative_tolerance,
                     "strands_over_tolerance": int(np.count_nonzero(~np.asarray(fit.converged)))}
    if params.model == "clothoid":
        report["fit"]["helix_elements"] = fit.settings["helix_elements"]  # the Super-Helix fit it started from
        report["fit"]["nodes"] = int((helix.n_elements + 1).sum())

    contacts = H = F = kin = None
    forces = np.zeros((0, 3))
    mu = np.zeros(0)
    if params.contacts != "none":
        from .contact import detect_contacts  # kept off the CLI's start
        from .contact.jacobian import contact_jacobian

        with timer.stage("kinematics"):
            kin = mod.kinematics(helix)
        with timer.stage("contacts"):
            pts, offsets, _, arc = mod.sample(helix, params.samples_per_element, kin)
            passes = int(params.contacts == "all") + int(head is not None)
            with progress(passes, "contacts", quiet, unit="pass") as bar:
                radius = params.wisp_radius if params.wisp_radius is not None else params.contact_radius
                contacts = detect_contacts(pts, offsets, arc, radius=radius,
                                           head=head, strand_strand=params.contacts == "all", progress=bar)
        with timer.stage("jacobian"):
            H = contact_jacobian(helix, contacts, kin)
        report["contacts"] = {"total": int(len(contacts.strand_a)),
                              "strand_strand": int(np.count_nonzero(np.asarray(contacts.strand_b) >= 0)),
                              "strand_head": int(np.count_nonzero(np.asarray(contacts.strand_b) < 0)),
                              "radius_m": float(contacts.radius)}
        mu = np.full(len(contacts.strand_a), material.friction)
        # the inverse problem keeps its forces strictly inside the friction cones (docs/stability.md): a force on
        # the cone boundary is an equilibrium that round-off tips into sliding
        mu_solve = (1.0 - params.friction_margin) * mu
        with timer.stage("solve"):
            F = mod.gravity_force(helix, material.linear_density, gravity, kin)
            redundant = redundant_strand_fraction(helix, contacts)

    # stable inversion (stabilize.py): solve, find the strands unstable with the contacts that hold them,
    # stiffen exactly those, solve again with the new K
    with timer.stage("stability"):
        ratio = _isolated_ratios_with_progress(helix, material, gravity, quiet)
    factor = np.ones(helix.n_strands)
    if params.stiffness_factor is not None:
        given = np.asarray(params.stiffness_factor, dtype=np.float64).reshape(-1)
        if given.shape != (helix.n_strands,) or not np.all(np.isfinite(given) & (given > 0)):
            raise ValueError(f"stiffness_factor must be {helix.n_strands} positive numbers, one per strand")
        factor = given.copy()
    held, rounds, history, admm_state = None, 0, [], None
    # stiffening rounds before the last are solved to a looser q0 tolerance (their forces only decide which strands
    # to stiffen); the forces written always come from a solve to the user's tolerance, and the stability verdict
    # is on those forces (docs/stability.md section 3)
    loose = _intermediate_q0_tolerance(params) if contacts is not None else None
    raised_ratio, raised_factor = np.zeros(helix.n_strands), factor.copy()
    while True:
        if contacts is not None:
            round_params = params if loose is None else replace(params, q0_tolerance=loose)
            with timer.stage("solve"):
                problem = build_inverse_problem(helix, F, H, material, gravity, params.guess, params.gamma, mu_solve,
                                                stiffness_factor=factor)
                # a re-solve after stiffening starts from the previous round's forces (Gauss-Seidel) or the
                # previous round's whole state (the strand-split ADMM: its multipliers too, rescaled for the new K)
                cp = problem.contact_problem(helix)
                geometry = admm_geometry(helix, contacts, kin)  # ADMM's strand systems in O(elements)
                if loose is not None and not history and solver_method(cp, params, redundant, geometry) != "admm":
                    loose = None  # only the strand-split ADMM carries its whole state into the next round
                    round_params = params
                solve = solve_inverse_problem(problem, helix, round_params, quiet, redundant,
                                              initial_forces=forces if history else None,
                                              initial_state=admm_state if history else None, cp=cp,
                                              geometry=geometry)
                del cp
            forces, admm_state = solve["forces"], solve.pop("admm_state", None)
            report["solve"] = {k: v for k, v in solve.items() if k != "forces"}
            report["solve"]["objective"] = problem.objective(forces.ravel())
            report["solve"]["cone_violation"] = cone_violation(forces, mu_solve)
            report["solve"]["friction_margin"] = params.friction_margin
            report["solve"]["gamma"] = params.gamma
            report["solve"]["guess"] = params.guess
            if not solve["converged"]:
                if params.strict or not solve.get("feasible"):
                    report["timings_s"] = dict(timer.stages)
                    raise SolverFailure(_failure_message(solve, params), solve["status"], solve["residual"], report)
                _accept_feasible(report["solve"], params)  # warned once, after the last round
            with timer.stage("rest_curvatures"):
                rest = rest_curvatures_with_contacts(helix, material, F, H, forces.ravel(), stiffness_factor=factor)
        else:
            with timer.stage("rest_curvatures"):
                rest = isolated_rest_curvatures(helix, material, gravity, stiffness_factor=factor)
        if params.stabilize == "none":
            break
        with timer.stage("stability_with_contacts"):
            held = held_stability(helix, material, gravity, contacts, forces, H, mu, ratio, quiet)
        step = stiffening_step(held.ratio, factor, params.stability_margin, params.max_stiffness_factor,
                               previous=(raised_ratio, raised_factor))
        history.append({"unstable": int(np.count_nonzero(held.ratio >= factor)),
                        "max_ratio": float(held.ratio.max()) if len(held.ratio) else 0.0,
                        "solve_iterations": int(report["solve"]["iterations"]) if contacts is not None else 0})
        if contacts is not None:
            history[-1]["q0_tolerance"] = round_params.q0_tolerance
        if params.stabilize != "stiffness" or step is None or rounds >= MAX_ROUNDS:
            if loose is not None and not _final_quality(report["solve"], params):
                loose = None  # solve once more to the user's tolerance (same factors) and check those forces
                continue
            break
        history[-1]["raised"] = int(np.count_nonzero(step > factor))
        up = step > factor  # each raised strand's rho at the factor it had (stiffening_step extrapolates from it)
        raised_ratio[up], raised_factor[up] = held.ratio[up], factor[up]
        factor, rounds = step, rounds + 1
        if loose is not None and rounds >= MAX_ROUNDS - TIGHT_ROUNDS:
            loose = None  # the last rounds to the user's tolerance: they stiffen what its forces still find unstable
    admm_state = None  # the last round's ADMM state holds its strand factors (1.25 GB on harolongo): not needed now
    if contacts is not None and report["solve"].get("warning"):
        warnings.warn(report["solve"]["warning"], FeasibleSolveWarning, stacklevel=2)

    extra = {}
    if params.discrete_rest_data:
        with timer.stage("discrete_rest_data"):
            extra, report["discrete_rest_data"] = discrete_rest_data(
                groom, helix, material, gravity, contacts, forces, params.rod_segments,
                stiffness_factor=factor if np.any(factor != 1.0) else None)

    with timer.stage("equilibrium_check"):
        residual = equilibrium_residuals(helix, rest, material, gravity, contacts, forces, stiffness_factor=factor)
    report["equilibrium"] = {"max_relative_residual": float(residual.max()) if len(residual) else 0.0,
                             "mean_relative_residual": float(residual.mean()) if len(residual) else 0.0}

    unstable = np.flatnonzero(ratio >= 1.0)
    report["stability"] = {
        "unstable_strands": int(len(unstable)),
        "criterion": "isolated strand: lambda_max(K^-1/2 dF/dq K^-1/2) < 1",
        "max_stiffness_ratio": float(ratio.max()) if len(ratio) else 0.0,
        "required_young_modulus_factor": float(max(1.0, ratio.max())) if len(ratio) else 1.0,
        "unstable_strand_ids": unstable[:100].tolist(),
        "note": ("isolated-strand criterion with the input material; strands longer than the Greenhill length "
                 f"{material.greenhill_length():.3f} m rising from the scalp are only held by contact"),
    }
    if held is not None:
        report["stability"]["unstable_with_contacts"] = int(np.count_nonzero(held.ratio >= factor))
        report["stability"]["criterion_with_contacts"] = HELD_CRITERION
        report["stability"]["stabilization"] = stabilization_report(
            params.stabilize, held.ratio, factor, held.kind, rounds, params.stability_margin,
            params.max_stiffness_factor)
        report["stability"]["stabilization"]["history"] = history
    if params.wisp_radius is not None:
        report["wisp"] = wisp_report(params.wisp_radius, material)
    report["timings_s"] = dict(timer.stages)
    report["timings_s"]["total"] = timer.total()
    report["parameters"] = {
        "tolerance_m": params.tolerance, "relative_tolerance": params.relative_tolerance,
        "contacts": params.contacts, "contact_radius_m": params.contact_radius, "wisp_radius_m": params.wisp_radius,
        "friction_margin": params.friction_margin, "stabilize": params.stabilize,
        "guess": params.guess,
        "gamma": params.gamma, "solver": params.solver, "solver_tolerance": params.solver_tolerance,
        "q0_tolerance": params.q0_tolerance, "strict": params.strict,
        "snap_roots": params.snap_roots, "model": params.model,
    }
    return InversionResult(groom=groom, head=head, params=params, helix=helix, rest_curvatures=rest,
                           fit_max_error=np.asarray(fit.max_error), fit_mean_error=np.asarray(fit.mean_error),
                           gravity=gravity, contacts=contacts, forces=forces, stiffness_ratio=ratio,
                           report=report, extra_arrays=extra, stiffness_factor=factor,
                           held_ratio=None if held is None else held.ratio)


DISCRETE_KEYS = ("rod_points", "rod_offsets", "cosserat_directors", "cosserat_rest_kappa", "cosserat_rest_sigma",
                 "cosserat_rest_lengths", "der_rest_lengths", "der_rest_kappa", "der_rest_twist", "der_frames")


def contact_point_forces(groom: Groom, helix: sh.SuperHelix, contacts, forces):
    """Contact forces as world point loads (strand, arc length along the input polyline, force):
    F_i^T r_i on strand a, its opposite on strand b; the fitted arc length is rescaled to the polyline's."""
    if contacts is None or len(forces) == 0:
        return None
    world = np.einsum("pji,pj->pi", np.asarray(contacts.frame), forces)
    strand_b = np.asarray(contacts.strand_b)
    on_b = strand_b >= 0
    strands = np.concatenate([np.asarray(contacts.strand_a), strand_b[on_b]])
    s = np.concatenate([np.asarray(contacts.s_a), np.asarray(contacts.s_b)[on_b]])
    f = np.concatenate([world, -world[on_b]])
    s_poly = s * groom.lengths()[strands] / helix.strand_lengths[strands]
    return strands, s_poly, f


def discrete_rest_data(groom: Groom, helix, material: Material, gravity, contacts, forces, segments=None, *,
                       stiffness_factor=None):
    """Cosserat (PyElastica) and DER rest data that make the groomed polylines an exact discrete
    equilibrium under gravity and the solved contact forces (docs/rest_data.md).  ``stiffness_factor``
    (S,): strand s is solved with moduli f_s E, f_s G (None: the material's own)."""
    if stiffness_factor is not None:     # a bad factor array is the caller's error, not the groom's
        stiffness_factor = strand_stiffness_factors(stiffness_factor, len(groom.offsets) - 1)
    loads = contact_point_forces(groom, helix, contacts, forces)
    try:
        rod = prepare_rods(groom.points, groom.offsets, segments)
        cos = cosserat_rest_data(groom.points, groom.offsets, material, gravity, loads, rod=rod,
                                 stiffness_factor=stiffness_factor)
        der = der_rest_data(groom.points, groom.offsets, material, gravity, loads, rod=rod,
                            stiffness_factor=stiffness_factor)
    except RestDataError as exc:
        raise GroomError(f"{groom.source}: discrete rest data: {exc} (try --rod-segments N)") from exc
    merged = {**cos, **der}
    arrays = {k: merged[k] for k in DISCRETE_KEYS}
    report = {"segments": "input vertices" if segments is None else int(segments),
              "cosserat_residual": cos["cosserat_residual"], "der_residual": der["der_residual"]}
    return arrays, report


WISP_PACKING = 0.5  # fraction of a wisp's cross-section filled by fibres


def wisp_report(wisp_radius: float, material: Material) -> dict:
    """What a strand standing for a wisp of radius R represents (docs/stability.md, section 5): about
    n = packing (R / a)^2 fibres of radius a.  A loose wisp (fibres not bonded) has n times a fibre's mass
    and n times its bending and twisting stiffness, so the rest curvatures and the stability ratios are a
    fibre's (K and F both scale by n); contact forces per wisp are n times those written."""
    n = WISP_PACKING * (wisp_radius / material.radius) ** 2
    return {"radius_m": float(wisp_radius), "fibres_per_strand": float(n), "packing": WISP_PACKING,
            "linear_density_kg_m": float(n * material.linear_density),
            "bending_stiffness_N_m2": float(n * material.bending_stiffness),
            "note": ("each strand is a loose wisp of about this many fibres: mass and stiffness scale together, "
                     "so the rest curvatures are a fibre's; the wisp radius is the contact radius; contact forces "
                     "of a wisp are fibres_per_strand times the forces written")}


HELD_CRITERION = ("per strand: lambda_max of K^-1/2 (dF/dq + dF_c/dq) K^-1/2 on the motions that keep its loaded head "
                  "contacts in place (3 rows sticking, the normal row on the cone boundary) < stiffness factor; "
                  "strand/strand forces as dead loads (a safe bound for the coupled groom)")


def held_stability(helix, material: Material, gravity, contacts, forces, H, mu, isolated_ratios, quiet=True):
    """Stiffness ratios with the contacts that hold each strand (stability.held_stiffness_ratios); without
    contacts, the isolated ratios."""
    S = helix.n_strands
    if contacts is None:
        return HeldStability(np.array(isolated_ratios, dtype=np.float64), np.zeros(S, np.int8),
                             np.zeros(S, np.int64), np.zeros(S, np.int64))
    with progress(S, "stability with contacts", quiet) as bar:
        return held_stiffness_ratios(helix, material.stiffness_diag, material.linear_density, gravity, contacts,
                                     forces, H, mu, isolated_ratios=isolated_ratios, progress=bar)


def _isolated_ratios_with_progress(helix, material, gravity, quiet):
    """The isolated-strand stiffness ratios (stability.stiffness_ratios) under a 'stability' bar."""
    with progress(helix.n_strands, "stability", quiet) as bar:
        return stiffness_ratios(helix, material.stiffness_diag, material.linear_density, gravity, progress=bar)


def _gap_summary(gaps: np.ndarray) -> dict:
    gaps = np.asarray(gaps, dtype=np.float64)
    return {"median_gap_m": float(np.median(np.abs(gaps))) if len(gaps) else 0.0,
            "max_gap_m": float(np.max(np.abs(gaps))) if len(gaps) else 0.0,
            "inside_head": int(np.count_nonzero(gaps < 0))}


def _snap_groom_roots(groom: Groom, head, snap_roots):
    """Translate every strand so that its root lies on the head surface; returns the gaps before."""
    roots = groom.points[groom.offsets[:-1]]
    snapped, gaps = snap_roots(roots, head)
    shift = np.repeat(snapped - roots, groom.counts, axis=0)
    moved = Groom(groom.points + shift, groom.offsets, up=groom.up, source=groom.source,
                  metadata=dict(groom.metadata))
    return moved, gaps


#: stiffening rounds before the last solve to this many times the user's q0 tolerance (at most LOOSE_Q0_MAX)
LOOSE_Q0_FACTOR = 10.0
LOOSE_Q0_MAX = 3e-2
#: the last stiffening rounds (of MAX_ROUNDS) are solved to the user's tolerance even when the looser ones have not
#: settled (harolongo: every round raises a few dozen strands, and the first solve to the user's tolerance finds
#: ~60 more unstable than the looser forces did)
TIGHT_ROUNDS = 2


def _intermediate_q0_tolerance(params: InversionParams) -> float | None:
    """The q0 tolerance of the stiffening rounds before the last (None: every solve to the user's): only with
    --stabilize stiffness and a q0 tolerance, LOOSE_Q0_FACTOR times it, at most LOOSE_Q0_MAX (never below it).
    The rounds' forces only decide which strands to stiffen; the written forces come from a solve to the user's
    tolerance and the stability verdict is on them (invert_groom).  Measured on example_groom(1000) and harolongo
    with all contacts: docs/stability.md section 3."""
    if params.stabilize != "stiffness" or params.q0_tolerance is None:
        return None
    loose = min(LOOSE_Q0_FACTOR * params.q0_tolerance, LOOSE_Q0_MAX)
    return loose if loose > params.q0_tolerance else None


def _final_quality(solve: dict, params: InversionParams) -> bool:
    """Whether a solve to a looser q0 tolerance is already what a solve to the user's would give: it stopped on the
    residual, or with a certified bound within the user's q0 tolerance, or it did not converge at all (a solve to
    the tighter tolerance, with the same budget, would not either)."""
    if not solve.get("converged"):
        return True
    if solve.get("stopped_on", "residual") != "q0_tolerance":
        return True
    bound = solve.get("q0_error_bound")
    return bound is not None and params.q0_tolerance is not None and bound <= params.q0_tolerance


def _failure_message(solve: dict, params: InversionParams) -> str:
    """What went wrong in the contact solve, how far it got, and what the user can do."""
    msg = (f"contact solver {solve['solver']} did not converge: status {solve['status']}, residual "
           f"{solve['residual']:.3e} after {solve['iterations']} iterations (target {params.solver_tolerance:.0e})")
    if solve.get("projected_sweeps") is not None:
        msg += (f"; at its rate it would need about {solve['projected_sweeps']:,.0f} sweeps (budget "
                f"{params.max_sweeps:,})")
    if solve.get("redundant_strand_fraction", 0.0) > AUTO_GS_MAX_REDUNDANT:
        msg += (f". The contacts are dense ({100 * solve['redundant_strand_fraction']:.0f} % of the strands that "
                "carry contacts have more contact rows than dofs; docs/solvers.md section 9)")
    if math.isfinite(solve["residual"]) and solve["residual"] > 0:
        accept = 10.0 ** math.ceil(math.log10(solve["residual"]))
        msg += (f". Any forces in their cones still make the groom an exact equilibrium, only less close to the "
                f"guess: --solver-tolerance {accept:.0e} accepts these forces")
        bound = solve.get("q0_error_bound")
        if bound is not None and math.isfinite(bound):
            msg += f" (their rest curvatures are certified within {bound:.1e}, relative, of the optimum's)"
        if params.strict:
            msg += "; without --strict they are written with status 'feasible'"
    return msg


def _accept_feasible(solve: dict, params: InversionParams) -> str:
    """An unconverged but feasible solve (not --strict): report status "feasible" (the solver's own status in
    "stopped_with") and the one-line warning (solve["warning"], issued by invert_groom after its last
    stabilisation round, not once per round); returns it."""
    solve["stopped_with"] = solve["status"]
    solve["status"] = "feasible"
    bound = solve.get("q0_error_bound")
    how = (f"rest curvatures certified within {bound:.1e} (relative) of the optimum's" if bound is not None
           and math.isfinite(bound) else "no bound on the rest curvatures' distance to the optimum's")
    msg = (f"contact solver {solve['solver']} stopped ({solve['stopped_with']}) at residual {solve['residual']:.1e} "
           f"after {solve['iterations']} iterations (target {params.solver_tolerance:.0e}): the forces lie in their "
           f"cones, so the groom is an exact equilibrium, with {how}; --strict refuses such results")
    solve["warning"] = msg
    return msg


