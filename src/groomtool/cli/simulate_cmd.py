"""``groom simulate`` and ``groom check``: the forward simulator on the command line.

Wiring (cli/main.py): ``simulate_cmd.add_parsers(sub)`` and the ``COMMANDS`` entries "simulate" and
"check".  Options shared with the other commands come from cli/options.py.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from .options import DEFAULT_TOLERANCE_M, add_input_options, add_material_options, material_from_args

EPILOG_SIMULATE = """examples:
  groom simulate out                      # an output directory of 'groom invert': its rest curvatures
  groom simulate strands.obj --head head.obj --seconds 2 -o sim   # a groom file: the naive set-up (rest = groomed shape)
  groom simulate out --dt 0.01 --format vtk --contacts head

outputs (in OUT): frame_0000.obj ... (polylines, metres), or frame_0000.vtu ... and frames.pvd, and simulation.json
"""

EPILOG_CHECK = """examples:
  groom check out
  groom check out --strands 50            # 50 random strands (seed 0) and their contact partners
  groom check out --seconds 2 --dt 0.002 --quiet

writes OUTDIR/check.json (atomically): tip drift and curvature-profile change of the inverted and of the
naive groom (rest = groomed shape) after the simulated time, contact solves that failed; exit code 0.
The inverted run uses the per-strand stiffness of rest.npz when the inversion wrote one; the naive run
the scalar material.  A run-time estimate is printed after the first steps (the very first step of a
fresh install also compiles the numerical kernels).
"""


def _add_simulation_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=float, default=1.0, help="simulated time, s (default 1)")
    p.add_argument("--dt", type=float, default=1.0 / 240.0, help="time step, s (default 1/240)")
    p.add_argument("--contacts", choices=["none", "head", "all"], default=None,
                   help="contacts to simulate (default: the inversion's mode; 'all' for a groom file)")
    p.add_argument("--contact-radius", type=float, default=None,
                   help="contact radius, m (default: the inversion's, else the contact module's default)")
    p.add_argument("--air-drag", type=float, default=0.0,
                   help="air drag per unit length, kg/(m s): force -c v (default 0)")
    p.add_argument("--damping", type=float, default=0.0, help="mass-proportional damping, 1/s (default 0)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar and no summary")


def add_parsers(subparsers) -> None:
    """Add ``simulate`` and ``check`` to the ``groom`` sub-command parsers."""
    sim = subparsers.add_parser("simulate", help="simulate a groom under gravity and frictional contact",
                                epilog=EPILOG_SIMULATE, formatter_class=argparse.RawDescriptionHelpFormatter)
    sim.add_argument("input", help="an output directory of 'groom invert' (or its rest.npz), or a groom file")
    sim.add_argument("--head", default=None, help="head mesh (default: the one stored in rest.npz, if any)")
    sim.add_argument("-o", "--output", default="simulation", help="output directory (default ./simulation)")
    sim.add_argument("--fps", type=float, default=24.0, help="frames written per simulated second (default 24)")
    sim.add_argument("--format", choices=["obj", "vtk"], action="append", default=None,
                     help="frame format, repeatable: obj (polylines) or vtk (.vtu per frame + frames.pvd); default obj")
    sim.add_argument("--tolerance", type=float, default=None,
                     help="fit tolerance for a groom file, in --units (default 0.5 mm)")
    _add_simulation_options(sim)
    add_input_options(sim)
    add_material_options(sim)

    chk = subparsers.add_parser("check", help="simulate an inverted groom and its naive set-up; write check.json",
                                epilog=EPILOG_CHECK, formatter_class=argparse.RawDescriptionHelpFormatter)
    chk.add_argument("outdir", help="an output directory of 'groom invert'")
    chk.add_argument("--strands", type=int, default=None,
                     help="check N strands drawn at random (with --seed), simulated with every strand in contact "
                          "with them (one level); figures over the N strands (default: all strands)")
    chk.add_argument("--seed", type=int, default=0, help="random seed of --strands (default 0)")
    _add_simulation_options(chk)


def _params(args):
    from ..groom import GroomError
    from ..simulate import SimulationParams

    for flag, value in (("--air-drag", args.air_drag), ("--damping", args.damping)):
        if not (0 <= value < np.inf):
            raise GroomError(f"{flag} must be >= 0 and finite, got {value:g}")
    if args.contact_radius is not None and not (0 < args.contact_radius < np.inf):
        raise GroomError(f"--contact-radius must be a positive length, got {args.contact_radius:g}")
    return SimulationParams(dt=args.dt, contacts=args.contacts or "none", contact_radius=args.contact_radius,
                            air_drag=args.air_drag, mass_damping=args.damping)


def _blas_single_thread():
    """One BLAS thread while simulating (per-strand systems of 30-200 dofs: threads only add contention)."""
    return threadpool_limits(limits=1, user_api="blas")


def _check_times(args) -> None:
    from ..groom import GroomError

    if not (args.seconds > 0 and args.dt > 0):
        raise GroomError(f"--seconds and --dt must be > 0 (got {args.seconds}, {args.dt})")
    if args.dt > args.seconds:
        raise GroomError(f"--dt {args.dt} is longer than --seconds {args.seconds}")


def _is_result(path: Path) -> bool:
    return (path.is_dir() and (path / "rest.npz").is_file()) or path.name.endswith(".npz")


def load_simulation_input(args):
    """(helix, rest curvatures, material, gravity, head, contact mode, radius, up, stiffness) from a result
    (either rod model: a Super Space Clothoid result gives a cl.SuperClothoid with nodal curvatures; stiffness:
    its per-strand K (S, N, 3), banded (diagonal, off-diagonal) blocks for a clothoid, or None) or a groom file
    (None)."""
    from ..groom import UNIT_SCALE, GroomError
    from ..io import load_groom, load_head

    path = Path(args.input)
    if _is_result(path):
        from ..check import load_inverted

        inv = load_inverted(path)
        head = load_head(args.head) if args.head else inv.head
        mode = args.contacts or inv.contacts
        radius = args.contact_radius if args.contact_radius is not None else inv.contact_radius
        return inv.helix, inv.rest_curvatures, inv.material, inv.gravity, head, mode, radius, inv.up, inv.stiffness()
    if path.is_dir():
        raise GroomError(f"{path}: a directory without rest.npz: give an output directory of 'groom invert'")
    from ..fit import fit_groom

    groom = load_groom(path, units=args.units, up=args.up, repair=args.repair, strand_length=args.strand_length)
    head = load_head(args.head, units=args.units) if args.head else None
    material = material_from_args(args)
    tolerance = DEFAULT_TOLERANCE_M if args.tolerance is None else args.tolerance * UNIT_SCALE[args.units]
    fit = fit_groom(groom, tolerance=tolerance, progress=not args.quiet)
    mode = args.contacts or "all"
    return (fit.helix, fit.helix.curvatures.copy(), material, groom.gravity(material.gravity), head, mode,
            args.contact_radius, groom.up, None)


def write_frames(result, outdir: Path, formats, up: str = "y") -> list[Path]:
    """One file per frame: OBJ polylines and/or VTK unstructured grids of lines with a frames.pvd index."""
    from ..groom import Groom
    from ..io import atomic_path, save_groom

    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    width = max(4, len(str(len(result.frames) - 1)))
    for k, pts in enumerate(result.frames):
        if "obj" in formats:
            path = outdir / f"frame_{k:0{width}d}.obj"
            save_groom(Groom(pts, result.offsets, up=up, source=f"frame {k} t={result.times[k]:.5f}s"), path)
            written.append(path)
        if "vtk" in formats:
            import meshio

            path = outdir / f"frame_{k:0{width}d}.vtu"
            mesh = meshio.Mesh(np.asarray(pts), [("line", _line_cells(result.offsets))])
            with atomic_path(path) as tmp:
                meshio.write(str(tmp), mesh, file_format="vtu")
            written.append(path)
    if "vtk" in formats:
        entries = "\n".join(f'    <DataSet timestep="{t:.6f}" file="frame_{k:0{width}d}.vtu"/>'
                            for k, t in enumerate(result.times))
        pvd = (f'<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n{entries}\n'
               "  </Collection>\n</VTKFile>\n")
        from ..io import atomic_write

        written.append(atomic_write(outdir / "frames.pvd", pvd))
    return written


def _line_cells(offsets: np.ndarray) -> np.ndarray:
    """(n_segments, 2) vertex pairs of every strand polyline."""
    idx = np.arange(offsets[-1])
    last = np.zeros(offsets[-1], dtype=bool)
    last[offsets[1:] - 1] = True
    start = idx[~last]
    return np.stack([start, start + 1], axis=1)


def cmd_simulate(args) -> int:
    """groom simulate: write the frames and simulation.json; exit code 0."""
    from ..io.results import write_json
    from ..simulate import simulate

    _check_times(args)
    t0 = time.perf_counter()
    helix, rest, material, gravity, head, mode, radius, up, stiffness = load_simulation_input(args)
    args.contacts = mode
    params = replace(_params(args), contact_radius=radius)
    with _blas_single_thread():
        result = simulate(helix, rest, material, gravity, head=head, seconds=args.seconds, frames_per_second=args.fps,
                          params=params, progress=not args.quiet, stiffness=stiffness)
    outdir = Path(args.output)
    formats = tuple(args.format) if args.format else ("obj",)
    write_frames(result, outdir, formats, up)
    report = {"input": str(args.input), "seconds": float(result.stats["seconds"]), "dt": args.dt,
              "steps": int(result.timings["steps"]), "frames": len(result.frames), "contacts": mode,
              "contact_radius_m": result.stats["contact_radius"], "strands": int(helix.n_strands),
              "solver_failures": int(result.stats["solver_failures"]),
              "per_strand_stiffness": stiffness is not None,
              "contacts_per_step_max": int(max(result.stats["contacts_per_step"], default=0)),
              "timings_s": result.timings, "total_s": time.perf_counter() - t0}
    write_json(outdir / "simulation.json", report)
    if not args.quiet:
        failures = report["solver_failures"]
        worst = max(result.stats["failed_residuals"], default=0.0)
        note = f"; {failures} contact solves did not converge (worst residual {worst:.1e})" if failures else ""
        print(f"groom simulate: {helix.n_strands} strands, {report['steps']} steps of {args.dt:.4g} s, "
              f"contacts {mode}: {result.timings['per_step'] * 1e3:.1f} ms/step; {len(result.frames)} frames "
              f"in {outdir} ({', '.join(formats)}){note}")
    return 0


def cmd_check(args) -> int:
    """groom check: simulate inverted and naive, write check.json, print a summary; exit code 0."""
    from ..check import check_groom, summary, write_check
    from ..groom import GroomError

    _check_times(args)
    path = Path(args.outdir)
    if not _is_result(path):
        raise GroomError(f"{path}: not an output directory of 'groom invert' (no rest.npz)")
    params = _params(args)
    with _blas_single_thread():
        report = check_groom(path, seconds=args.seconds, contacts=args.contacts, params=params,
                             progress=not args.quiet, strands=args.strands, seed=args.seed)
    out = write_check(path, report)
    if not args.quiet:
        print(summary(report))
        print(f"  wrote     {out}")
    return 0
