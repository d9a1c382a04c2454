"""``groom check``: does an inverted groom stay put?  Two simulations from the groomed shape.

* inverted: rest curvatures q0 from the inversion (rest.npz);
* naive:    q0 = q, the groomed shape taken as the rest shape (what one gets without inversion).

Both start at rest from the fitted rods (Super-Helices, or Super Space Clothoids for a ``--model clothoid``
result: nodal curvatures, their velocity terms A(q, qd) dropped, which is exact at rest), with the same
material, gravity, head and contact
mode as the inversion (report.json) unless overridden.  Measured after ``seconds`` of simulated time:

    tip drift (per strand)   |x_tip(T) - x_tip(0)|                         (m)
    tip excursion            max over the steps of |x_tip(t) - x_tip(0)|   (m)
    curvature change         max_j | |kappa_j(T)| - |kappa_j(0)| | / max_j |kappa_j(0)|,
                             |kappa_j| = sqrt(kappa1^2 + kappa2^2) on element j (the curl profile)

Per-strand materials: when rest.npz carries ``strand_young_modulus`` and/or ``strand_shear_modulus``
(S,) (Pa; written by an inversion that stiffened strands, with ``stiffness_factor`` (S,)), the
inverted run uses K_s = l_j (G_s 2I, E_s I, E_s I) per strand (the moduli already include the
factor); with only ``stiffness_factor``, K_s = factor_s x the scalar material's.  The naive run keeps
the scalar material: it is what the user's groom does without inversion.

Subset (``strands=n``): n strands drawn at random (numpy default_rng(seed), without replacement)
plus every strand sharing a contact with one of them (one level: the partners' own partners are
left out), from the inversion's contacts, else from a detection on the groomed shape.  Both runs
simulate that set; drift and curvature figures are over the n drawn strands only.  In the inverted
run the partners' contacts with strands left out act as constant forces, the inversion's (the set
starts in equilibrium; they do not follow the motion); the naive run has no such forces.
"""

from __future__ import annotations

import gc
import time
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .io.results import read_result
from .material import Material
from .rods import clothoid as cl
from .rods import superhelix as sh
from .simulate import SimulationParams, simulate


@dataclass
class InvertedGroom:
    """What a simulation needs from an output directory of ``groom invert``."""

    helix: sh.SuperHelix  # or cl.SuperClothoid (rest.npz model "clothoid": nodal curvatures (S, N + 1, 3))
    rest_curvatures: np.ndarray
    material: Material
    gravity: np.ndarray
    head: object  # trimesh.Trimesh or None
    contacts: str  # the inversion's contact mode
    contact_radius: float | None
    source: str
    up: str
    stiffness_ratio: np.ndarray | None = None  # per strand; >= 1: unstable without contacts (stability.py)
    contact_forces: tuple | None = None  # (contacts record, forces (m, 3) N) of the inversion
    strand_stiffness: np.ndarray | None = None  # (S, 3) per unit length (GJ_s, EI_s, EI_s), per-strand materials
    stiffness_factor: np.ndarray | None = None  # (S,) as written by the inversion, if any
    boundary_force: np.ndarray | None = None  # (S, N, 3) of a subset: the inversion's forces of the strands left out

    def per_strand(self) -> bool:
        """True when some strand's stiffness differs from the scalar material's."""
        if self.strand_stiffness is None:
            return False
        scalar = np.asarray(self.material.stiffness_diag)[None, :]
        return not np.allclose(self.strand_stiffness, scalar, rtol=1e-12, atol=0.0)

    @property
    def model(self) -> str:
        """"clothoid" or "superhelix"."""
        return "clothoid" if isinstance(self.helix, cl.SuperClothoid) else "superhelix"

    def stiffness(self) -> np.ndarray | None:
        """K (S, N, 3) = l_j (GJ_s, EI_s, EI_s) of the per-strand materials, None without them (clothoid: the banded
        (diagonal (S, N + 1, 3), off-diagonal (S, N, 3)) blocks of cl.stiffness with D_s = (GJ_s, EI_s, EI_s))."""
        if self.strand_stiffness is None:
            return None
        if isinstance(self.helix, cl.SuperClothoid):
            diag, off = cl.stiffness(self.helix, np.ones(3))
            return diag * self.strand_stiffness[:, None, :], off * self.strand_stiffness[:, None, :]
        return self.helix.lengths[..., None] * self.strand_stiffness[:, None, :]

    def subset(self, strands) -> "InvertedGroom":
        """The same inversion restricted to ``strands`` (indices, in that order); contacts between them kept."""
        idx = np.asarray(strands, dtype=np.int64)
        h = self.helix
        rod = cl.SuperClothoid if isinstance(h, cl.SuperClothoid) else sh.SuperHelix
        helix = rod(h.root_positions[idx], h.root_frames[idx], h.lengths[idx], h.curvatures[idx], h.n_elements[idx])
        forces = None
        if self.contact_forces is not None:
            record, f = self.contact_forces
            new_index = np.full(h.n_strands, -1, dtype=np.int64)
            new_index[idx] = np.arange(len(idx))
            a = np.asarray(record.strand_a)
            b = np.asarray(record.strand_b)
            keep = (new_index[a] >= 0) & ((b < 0) | (new_index[np.maximum(b, 0)] >= 0))
            forces = (SimpleNamespace(strand_a=new_index[a[keep]], s_a=np.asarray(record.s_a)[keep],
                                      strand_b=np.where(b[keep] < 0, b[keep], new_index[np.maximum(b[keep], 0)]),
                                      s_b=np.asarray(record.s_b)[keep]), f[keep])

        def pick(x):
            return None if x is None else np.asarray(x)[idx]

        boundary = None
        if self.contact_forces is not None and getattr(self.contact_forces[0], "frame", None) is not None:
            from .contact.jacobian import generalized_contact_force

            record, f = self.contact_forces
            a, b = np.asarray(record.strand_a), np.asarray(record.strand_b)
            inside = np.zeros(h.n_strands, dtype=bool)
            inside[idx] = True
            cut = (b >= 0) & (inside[a] != inside[np.maximum(b, 0)])
            if np.any(cut):
                part = SimpleNamespace(strand_a=a[cut], s_a=np.asarray(record.s_a)[cut], strand_b=b[cut],
                                       s_b=np.asarray(record.s_b)[cut], frame=record.frame[cut])
                boundary = generalized_contact_force(h, part, f[cut])[idx]
        return replace(self, helix=helix, rest_curvatures=self.rest_curvatures[idx], contact_forces=forces,
                       boundary_force=boundary,
                       stiffness_ratio=pick(self.stiffness_ratio), strand_stiffness=pick(self.strand_stiffness),
                       stiffness_factor=pick(self.stiffness_factor))


def load_inverted(outdir) -> InvertedGroom:
    """Read rest.npz (and report.json when present) of an inversion output directory (either rod model)."""
    saved = read_result(outdir)
    helix = saved.rod()
    material = saved.material
    strand_stiffness, factor = saved.per_strand_stiffness(material)
    return InvertedGroom(helix=helix, rest_curvatures=saved.rest_curvatures, material=material, gravity=saved.gravity,
                         head=saved.head(), contacts=saved.contacts, contact_radius=saved.contact_radius,
                         source=str(saved.arrays.get("source", outdir)), up=saved.up,
                         stiffness_ratio=saved.stiffness_ratio, contact_forces=saved.contact_forces,
                         strand_stiffness=strand_stiffness, stiffness_factor=factor)


def tip_drifts(tips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per strand: final drift |x(T) - x(0)| and excursion max_t |x(t) - x(0)|; tips (steps + 1, S, 3)."""
    d = np.linalg.norm(tips - tips[0], axis=-1)
    return d[-1], d.max(axis=0)


def curvature_profile_change(before: sh.SuperHelix, after_curvatures: np.ndarray) -> np.ndarray:
    """Per strand max_j | |kappa_j(T)| - |kappa_j(0)| | / max_j |kappa_j(0)| (bending curvature only; j the elements
    of a Super-Helix, the nodes of a Super Space Clothoid)."""
    mask = before.node_mask if isinstance(before, cl.SuperClothoid) else before.element_mask
    k0 = np.linalg.norm(before.curvatures[..., 1:], axis=-1) * mask
    k1 = np.linalg.norm(np.asarray(after_curvatures)[..., 1:], axis=-1) * mask
    scale = np.max(k0, axis=1)
    change = np.max(np.abs(k1 - k0), axis=1)
    return np.divide(change, scale, out=np.zeros_like(change), where=scale > 0)


def _stats(values: np.ndarray) -> dict:
    values = np.asarray(values, dtype=np.float64)
    return {"max": float(values.max()) if values.size else 0.0, "mean": float(values.mean()) if values.size else 0.0}


def run_summary(result, helix0: sh.SuperHelix, stiffness_ratio=None, strands=None) -> dict:
    """The figures of one simulation for check.json (drift also split by stability in isolation when
    the stiffness ratios are known: a strand with ratio >= 1 can only be held by contacts); over
    ``strands`` (indices) only when given."""
    drift, excursion = tip_drifts(result.tips)
    curv = curvature_profile_change(helix0, result.final.curvatures)
    if strands is not None:
        drift, excursion, curv = drift[strands], excursion[strands], curv[strands]
        stiffness_ratio = None if stiffness_ratio is None else np.asarray(stiffness_ratio)[strands]
    st = result.stats
    split = {}
    if stiffness_ratio is not None:
        unstable = np.asarray(stiffness_ratio) >= 1.0
        split = {"max_tip_drift_stable_strands_m": float(drift[~unstable].max()) if np.any(~unstable) else None,
                 "max_tip_drift_unstable_strands_m": float(drift[unstable].max()) if np.any(unstable) else None}
    return {
        "max_tip_drift_m": float(drift.max()) if drift.size else 0.0,
        "mean_tip_drift_m": float(drift.mean()) if drift.size else 0.0,
        "max_tip_excursion_m": float(excursion.max()) if excursion.size else 0.0,
        **split,
        "curvature_profile_change": _stats(curv),
        "contacts_per_step": _stats(st["contacts_per_step"]),
        "modified_step_matrices": int(st["modified_step_matrices"]),
        "rate_limited_strand_steps": int(st["rate_limited_strand_steps"]),
        "solver": {"failures": int(st["solver_failures"]), "solves": len(st["solver_residuals"]),
                   "failed_steps": [int(k) for k in st.get("failed_steps", [])][:100],
                   "worst_failed_residual": float(max(st.get("failed_residuals", []), default=0.0)),
                   "max_residual": float(max(st["solver_residuals"], default=0.0)),
                   "mean_iterations": float(np.mean(st["solver_iterations"])) if st["solver_iterations"] else 0.0},
        "detection": {"passes": int(st.get("detection_passes", 0)), "reused": int(st.get("detection_reused", 0)),
                      "head_redetections": int(st.get("head_redetections", 0))},
        "steps_at_rest": int(st.get("steps_at_rest", 0)),
        "steps_partially_assembled": int(st.get("steps_partially_assembled", 0)),
        "timings_s": {k: float(v) for k, v in result.timings.items()},
    }


def choose_strands(inv: InvertedGroom, n: int, seed: int = 0, radius: float | None = None,
                   contacts: str = "all") -> tuple[np.ndarray, np.ndarray]:
    """(chosen, simulated): n strands drawn with numpy default_rng(seed) (sorted), and those plus every
    strand sharing a contact with one of them (the inversion's contacts, else a detection on the
    groomed shape at ``radius``), sorted."""
    S = inv.helix.n_strands
    if not 1 <= n:
        raise ValueError(f"--strands must be >= 1, got {n}")
    chosen = np.sort(np.random.default_rng(seed).choice(S, size=min(n, S), replace=False))
    if n >= S:
        return chosen, chosen
    if inv.contact_forces is not None:
        a, b = np.asarray(inv.contact_forces[0].strand_a), np.asarray(inv.contact_forces[0].strand_b)
    elif contacts == "all":
        from .contact import DEFAULT_CONTACT_RADIUS, detect_strand_contacts

        pts, offsets, _, arc = (cl if isinstance(inv.helix, cl.SuperClothoid) else sh).sample(inv.helix, 8)
        found = detect_strand_contacts(pts, offsets, arc, DEFAULT_CONTACT_RADIUS if radius is None else radius)
        a, b = found.strand_a, found.strand_b
    else:
        a = b = np.zeros(0, dtype=np.int64)
    pair = b >= 0
    a, b = a[pair], b[pair]
    picked = np.zeros(S, dtype=bool)
    picked[chosen] = True
    partners = np.concatenate([b[picked[a]], a[picked[b]]])
    return chosen, np.union1d(chosen, partners)


def check_groom(outdir, seconds: float = 1.0, dt: float | None = None, contacts: str | None = None,
                params: SimulationParams | None = None, progress: bool = False, strands: int | None = None,
                seed: int = 0) -> dict:
    """Simulate the inverted and the naive groom from the groomed shape; returns the check report.

    ``params`` carries the options (dt, contacts and contact_radius override it on a copy when given;
    unset, the inversion's contact mode and radius are used); ``strands``: check a random subset
    with its contact partners (module docstring); ``progress``: a bar and a run-time estimate."""
    from .simulate_progress import StepProgress

    t0 = time.perf_counter()
    inv = load_inverted(outdir)
    base = params or SimulationParams()
    mode = contacts or inv.contacts
    base = replace(base, dt=base.dt if dt is None else dt, contacts=mode,
                   contact_radius=base.contact_radius if base.contact_radius is not None else inv.contact_radius)
    dt = base.dt
    total_strands = int(inv.helix.n_strands)
    chosen = None
    if strands is not None:
        picked, simulated = choose_strands(inv, strands, seed, base.contact_radius, mode)
        inv = inv.subset(simulated)
        chosen = np.searchsorted(simulated, picked)
    steps = int(round(seconds / dt))
    report = {"input": str(outdir), "strands": int(inv.helix.n_strands), "elements": int(inv.helix.n_elements.sum()),
              "seconds": float(seconds), "dt": float(dt), "steps": steps, "contacts": mode,
              "contact_radius_m": base.contact_radius, "head": inv.head is not None,
              "unstable_in_isolation": None if inv.stiffness_ratio is None else int(np.sum(inv.stiffness_ratio >= 1.0)),
              "per_strand_materials": inv.per_strand(), "model": inv.model,
              "contact_solve": {"tolerance": base.solver_tolerance, "max_sweeps": base.max_sweeps}}
    if inv.model == "clothoid" and not (base.velocity_terms and base.clothoid_velocity_terms):
        report["velocity_terms"] = ("dropped: A(q, qd) is not computed for Super Space Clothoids (zero at rest, so "
                                    "the inverted run is exact; the naive run's sag omits the Coriolis and "
                                    "centrifugal terms)")
    if chosen is not None:
        report["subset"] = {"groom_strands": total_strands, "checked": int(len(chosen)), "seed": int(seed),
                            "simulated_with_partners": int(inv.helix.n_strands),
                            "checked_strands": [int(k) for k in np.asarray(simulated)[chosen]]}
    bar = StepProgress([("inverted", steps), ("naive", steps)], enabled=progress)
    try:
        for name, rest, stiffness in (("inverted", inv.rest_curvatures, inv.stiffness()),
                                      ("naive", inv.helix.curvatures.copy(), None)):
            result = simulate(inv.helix, rest, inv.material, inv.gravity, head=inv.head, seconds=seconds,
                              frames_per_second=1.0, params=base, progress=bar, stiffness=stiffness,
                              warm_start=inv.contact_forces if name == "inverted" else None,
                              external_force=inv.boundary_force if name == "inverted" else None)
            report[name] = run_summary(result, inv.helix, inv.stiffness_ratio, chosen)
            if report["contact_radius_m"] is None:
                report["contact_radius_m"] = result.stats["contact_radius"]
            # the run's frames, tips and state are summarised: released (and the simulator's reference cycles
            # collected) before the next run builds its own
            del result
            gc.collect()
            if name == "inverted":
                bar.next_run()
    finally:
        bar.close()
    naive = report["naive"]["max_tip_drift_m"]
    report["drift_ratio"] = report["inverted"]["max_tip_drift_m"] / naive if naive > 0 else 0.0
    report["timings_s"] = {"total": time.perf_counter() - t0}
    return report


def write_check(outdir, report: dict) -> Path:
    """check.json beside rest.npz, written atomically."""
    from .io.results import write_json

    folder = Path(outdir) if Path(outdir).is_dir() else Path(outdir).parent
    path = folder / "check.json"
    write_json(path, report)
    return path


def summary(report: dict) -> str:
    """A few lines for the terminal."""
    inv, nai = report["inverted"], report["naive"]

    def run(name, r):
        return (f"  {name:<9} tip drift max {r['max_tip_drift_m'] * 1e3:.4f} mm, mean {r['mean_tip_drift_m'] * 1e3:.4f} mm;"
                f" curvature change max {r['curvature_profile_change']['max'] * 100:.3f} %")

    sub = report.get("subset")
    what = (f"{sub['checked']} of {sub['groom_strands']} strands (seed {sub['seed']}; simulated with their contact "
            f"partners: {sub['simulated_with_partners']})" if sub else f"{report['strands']} strands")
    model = " (Super Space Clothoids)" if report.get("model") == "clothoid" else ""
    lines = [f"groom check: {what}{model}, {report['seconds']:g} s simulated at "
             f"dt = {report['dt']:.4g} s ({report['steps']} steps), contacts {report['contacts']}",
             run("inverted", inv), run("naive", nai),
             f"  ratio     inverted / naive max drift = {report['drift_ratio']:.2e}"]
    if report.get("velocity_terms"):
        lines.append("  model     clothoid velocity terms A(q, qd) dropped (exact at rest; the naive sag omits them)")
    if report.get("per_strand_materials"):
        lines.append("  material  inverted run with the per-strand stiffness of rest.npz; naive run with the scalar material")
    lines.append("  contact   " + "; ".join(_solver_line(name, report[name]["solver"]) for name in ("inverted", "naive")))
    solve = report.get("contact_solve")
    if solve and any(report[name]["solver"]["failures"] for name in ("inverted", "naive")):
        lines.append(f"            (failed: the step's Coulomb solve did not reach residual {solve['tolerance']:.0e} in "
                     f"{solve['max_sweeps']} sweeps; its impulses are used as they are, docs/simulation.md section 6)")
    if report.get("unstable_in_isolation"):
        drift = inv.get("max_tip_drift_unstable_strands_m")
        # with --strands the drifts are over the checked strands, which may hold none of them
        their = (f"their inverted max drift: {drift * 1e3:.4f} mm" if drift is not None
                 else "none of them is among the checked strands")
        among = (f" of the {report['strands']} simulated" if report.get("subset") else "")
        lines.append(f"  note      {report['unstable_in_isolation']}{among} strands are unstable without contacts "
                     f"(stiffness ratio >= 1); {their}")
    lines.append(f"  time      {report['timings_s']['total']:.1f} s ({inv['timings_s']['per_step'] * 1e3:.1f} ms/step "
                 f"inverted, {nai['timings_s']['per_step'] * 1e3:.1f} ms/step naive)")
    return "\n".join(lines)


def _solver_line(name: str, solver: dict) -> str:
    """'inverted: 0 of 240 solves failed' or '... 3 of 240 failed (worst residual 2e-06, steps 4, 7, 9)'."""
    failed = solver["failures"]
    text = f"{name}: {failed} of {solver.get('solves', '?')} contact solves failed"
    if failed:
        steps = solver.get("failed_steps", [])
        shown = ", ".join(str(k) for k in steps[:5]) + (", ..." if len(steps) > 5 else "")
        text += f" (worst residual {solver.get('worst_failed_residual', solver['max_residual']):.1e}, steps {shown})"
    return text
