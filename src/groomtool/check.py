"""``groom check``: does an inverted groom stay put?  Two simulations from the groomed shape.

* inverted: rest curvatures q0 from the inversion (rest.npz);
* naive:    q0 = q, the groomed shape taken as the rest shape (what one gets without inversion).

Both start at rest from the fitted Super-Helices, with the same material, gravity, head and contact
mode as the inversion (report.json) unless overridden.  Measured after ``seconds`` of simulated time:

    tip drift (per strand)   |x_tip(T) - x_tip(0)|                         (m)
    tip excursion            max over the steps of |x_tip(t) - x_tip(0)|   (m)
    curvature change         max_j | |kappa_j(T)| - |kappa_j(0)| | / max_j |kappa_j(0)|,
                             |kappa_j| = sqrt(kappa1^2 + kappa2^2) on element j (the curl profile)
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from .material import Material
from .rods import superhelix as sh
from .simulate import SimulationParams, simulate


@dataclass
class InvertedGroom:
    """What a simulation needs from an output directory of ``groom invert``."""

    helix: sh.SuperHelix
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


def load_inverted(outdir) -> InvertedGroom:
    """Read rest.npz (and report.json when present) of an inversion output directory."""
    import trimesh

    from .viz import fields

    arrays = fields.load_arrays(outdir)
    helix = fields.helix(arrays)
    rest = fields.helix(arrays, rest=True).curvatures

    def scalar(name, default):
        return float(arrays[name]) if name in arrays else default

    d = Material()
    material = Material(young_modulus=scalar("young_modulus", d.young_modulus), radius=scalar("radius", d.radius),
                        density=scalar("density", d.density), friction=scalar("friction", d.friction),
                        shear_modulus=scalar("shear_modulus", None) if "shear_modulus" in arrays else None)
    gravity = np.asarray(arrays.get("gravity", [0.0, -d.gravity, 0.0]), dtype=np.float64).reshape(3)
    mesh = fields.head_mesh(arrays)
    head = trimesh.Trimesh(mesh[0], mesh[1], process=False) if mesh is not None else None
    report = {}
    folder = Path(outdir) if Path(outdir).is_dir() else Path(outdir).parent
    if (folder / "report.json").is_file():
        from .io.result_check import read_report

        report = read_report(folder)
    params = report.get("parameters", {})
    contacts = params.get("contacts", "all" if head is not None else "none")
    radius = scalar("contact_radius", None) if "contact_radius" in arrays else None
    if radius is None or not np.isfinite(radius):  # NaN: written without contacts
        radius = report.get("contacts", {}).get("radius_m") or params.get("contact_radius_m")
    ratio = np.asarray(arrays.get("stiffness_ratio", np.zeros(0)), dtype=np.float64)
    forces = None
    if len(arrays.get("contact_forces", ())):
        record = SimpleNamespace(strand_a=np.asarray(arrays["contact_strand_a"]), s_a=np.asarray(arrays["contact_s_a"]),
                                 strand_b=np.asarray(arrays["contact_strand_b"]), s_b=np.asarray(arrays["contact_s_b"]))
        forces = (record, np.asarray(arrays["contact_forces"], dtype=np.float64).reshape(-1, 3))
    return InvertedGroom(helix=helix, rest_curvatures=rest, material=material, gravity=gravity, head=head,
                         contacts=contacts, contact_radius=radius, source=str(arrays.get("source", outdir)),
                         up=fields.up_axis(arrays), stiffness_ratio=ratio if ratio.size == helix.n_strands else None,
                         contact_forces=forces)


def tip_drifts(tips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per strand: final drift |x(T) - x(0)| and excursion max_t |x(t) - x(0)|; tips (steps + 1, S, 3)."""
    d = np.linalg.norm(tips - tips[0], axis=-1)
    return d[-1], d.max(axis=0)


def curvature_profile_change(before: sh.SuperHelix, after_curvatures: np.ndarray) -> np.ndarray:
    """Per strand max_j | |kappa_j(T)| - |kappa_j(0)| | / max_j |kappa_j(0)| (bending curvature only)."""
    k0 = np.linalg.norm(before.curvatures[..., 1:], axis=-1) * before.element_mask
    k1 = np.linalg.norm(np.asarray(after_curvatures)[..., 1:], axis=-1) * before.element_mask
    scale = np.max(k0, axis=1)
    change = np.max(np.abs(k1 - k0), axis=1)
    return np.divide(change, scale, out=np.zeros_like(change), where=scale > 0)


def _stats(values: np.ndarray) -> dict:
    values = np.asarray(values, dtype=np.float64)
    return {"max": float(values.max()) if values.size else 0.0, "mean": float(values.mean()) if values.size else 0.0}


def run_summary(result, helix0: sh.SuperHelix, stiffness_ratio=None) -> dict:
    """The figures of one simulation for check.json (drift also split by stability in isolation when
    the stiffness ratios are known: a strand with ratio >= 1 can only be held by contacts)."""
    drift, excursion = tip_drifts(result.tips)
    curv = curvature_profile_change(helix0, result.final.curvatures)
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
        "solver": {"failures": int(st["solver_failures"]),
                   "max_residual": float(max(st["solver_residuals"], default=0.0)),
                   "mean_iterations": float(np.mean(st["solver_iterations"])) if st["solver_iterations"] else 0.0},
        "timings_s": {k: float(v) for k, v in result.timings.items()},
    }


def check_groom(outdir, seconds: float = 1.0, dt: float = 1.0 / 240.0, contacts: str | None = None,
                params: SimulationParams | None = None, progress: bool = False) -> dict:
    """Simulate the inverted and the naive groom from the groomed shape; returns the check report."""
    t0 = time.perf_counter()
    inv = load_inverted(outdir)
    mode = contacts or inv.contacts
    base = params or SimulationParams()
    base = replace(base, dt=dt, contacts=mode,
                   contact_radius=base.contact_radius if base.contact_radius is not None else inv.contact_radius)
    report = {"input": str(outdir), "strands": int(inv.helix.n_strands), "elements": int(inv.helix.n_elements.sum()),
              "seconds": float(seconds), "dt": float(dt), "steps": int(round(seconds / dt)), "contacts": mode,
              "contact_radius_m": base.contact_radius, "head": inv.head is not None,
              "unstable_in_isolation": None if inv.stiffness_ratio is None else int(np.sum(inv.stiffness_ratio >= 1.0))}
    for name, rest in (("inverted", inv.rest_curvatures), ("naive", inv.helix.curvatures.copy())):
        result = simulate(inv.helix, rest, inv.material, inv.gravity, head=inv.head, seconds=seconds, dt=dt,
                          contacts=mode, frames_per_second=1.0, params=base, progress=progress,
                          warm_start=inv.contact_forces if name == "inverted" else None)
        report[name] = run_summary(result, inv.helix, inv.stiffness_ratio)
        if report["contact_radius_m"] is None:
            report["contact_radius_m"] = result.stats["contact_radius"]
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

    lines = [f"groom check: {report['strands']} strands, {report['seconds']:g} s simulated at "
             f"dt = {report['dt']:.4g} s ({report['steps']} steps), contacts {report['contacts']}",
             run("inverted", inv), run("naive", nai),
             f"  ratio     inverted / naive max drift = {report['drift_ratio']:.2e}"]
    if report.get("unstable_in_isolation"):
        lines.append(f"  note      {report['unstable_in_isolation']} strands are unstable without contacts (stiffness "
                     f"ratio >= 1); their inverted max drift: {inv['max_tip_drift_unstable_strands_m'] * 1e3:.4f} mm")
    lines.append(f"  time      {report['timings_s']['total']:.1f} s ({inv['timings_s']['per_step'] * 1e3:.1f} ms/step "
                 f"inverted, {nai['timings_s']['per_step'] * 1e3:.1f} ms/step naive)")
    return "\n".join(lines)
