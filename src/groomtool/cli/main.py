"""The ``groom`` command line.

Exit codes: 0 success, 1 user error (bad input, bad option), 2 a solver did not converge, 3 internal
error (a bug, one line; GROOM_DEBUG=1 shows the traceback), 130 interrupted.
All lengths inside are metres; ``--units`` states the unit of the input files and is converted.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from ..solver_choice import Q0_TOLERANCE  # --q0-tolerance default (docs/solvers.md section 11)
from ..version import __version__
from . import batch_cmd, export_cmd, simulate_cmd, view_cmd
from .options import (EXIT_INTERNAL_ERROR, EXIT_NOT_CONVERGED, EXIT_OK, EXIT_USER_ERROR, MODEL_CHOICES, UserError,
                      add_input_options, add_material_options, add_scale_option, cli_message, invert_params)


class _Parser(argparse.ArgumentParser):
    """argparse that exits with 1 (user error) on a bad option, keeping 2 for "did not converge"."""

    def error(self, message):
        self.print_usage(sys.stderr)
        self.exit(EXIT_USER_ERROR, f"{self.prog}: error: {message}\n")


EPILOG_INVERT = """examples:
  groom invert strands.obj --head head.obj -o out --contacts all
  groom invert harolongo.data --units cm --head head.obj --contacts head --snap-roots
  groom invert guides.hair --up z --tolerance 2e-4 --young 2.5e9 --radius 35e-6 --quiet

outputs (in OUTDIR, written as one atomic set): rest.npz, rest_shape.obj, fitted.obj, report.json
exit codes: 0 ok, 1 user error, 2 solver did not converge (with --strict; nothing written)
"""


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="groom", description="Hair grooming and inversion: rest curvatures that make a groom an equilibrium.")
    parser.add_argument("--version", action="version", version=f"groom (groomtool) {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    inv = sub.add_parser("invert", help="compute rest curvatures that hold the groom in place",
                         epilog=EPILOG_INVERT, formatter_class=argparse.RawDescriptionHelpFormatter)
    inv.add_argument("input", help="groom file: .obj (polylines), .data (USC-HairSalon), .hair (Cem Yuksel), .ply (edges), "
                                   ".usd/.usda/.usdc/.usdz (BasisCurves), .abc (Alembic curves; pip install "
                                   "'groomtool[alembic]')")
    inv.add_argument("--head", default=None, help="head mesh (.obj, .ply, .stl), same units as the input")
    inv.add_argument("-o", "--output", default="groom_out", help="output directory (default ./groom_out)")
    add_input_options(inv)
    add_scale_option(inv)
    inv.add_argument("--tolerance", type=float, default=None,
                     help="max distance of the input points to the fitted helices, in --units (default 0.5 mm)")
    inv.add_argument("--relative-tolerance", type=float, default=None,
                     help="fit tolerance as a fraction of each strand's length (the smaller of both applies)")
    inv.add_argument("--contacts", choices=["none", "head", "all"], default="none",
                     help="contacts to account for: none (isolated strands), head, all (head and strand/strand)")
    inv.add_argument("--contact-radius", type=float, default=None,
                     help="contact thickness around each strand axis, in --units (default: see docs/contact.md)")
    inv.add_argument("--wisp-radius", type=float, default=None, metavar="R",
                     help="each strand stands for a wisp of hair of radius R (in --units): guide strands of USC-style "
                          "data; R is then the contact radius, so guides rest on the head and on each other as "
                          "wisps do (docs/stability.md)")
    inv.add_argument("--snap-roots", action="store_true",
                     help="move each strand so its root lies on the head surface (else the gap is reported)")
    inv.add_argument("--guess", choices=["current", "tip"], default="current",
                     help="rest-curvature guess of the inverse problem: the groomed curvatures, or each strand's tip curvature")
    inv.add_argument("--gamma", type=float, default=None,
                     help="regularisation of the contact forces, relative to the Delassus diagonal (default 1e-4; see docs/maths.md)")
    inv.add_argument("--solver", choices=["clarabel", "gs", "admm", "auto"], default="auto",
                     help="contact solver: clarabel (interior point, polished by Gauss-Seidel; up to ~10k contacts), "
                          "gs (Gauss-Seidel), admm (the strand-split ADMM for dense contacts), auto (gs for sparse "
                          "contacts, admm for dense ones beyond 10k, else clarabel; see docs/cli.md)")
    inv.add_argument("--solver-tolerance", type=float, default=1e-8, metavar="TOL",
                     help="optimality of the contact forces: the scaled natural-map residual to reach (default "
                          "1e-8; any forces in their cones give an exact equilibrium, this only decides how close "
                          "the rest curvatures are to the guess; see docs/solvers.md)")
    inv.add_argument("--max-sweeps", type=int, default=5000, metavar="N",
                     help="Gauss-Seidel sweep budget of the contact solve (default 5000)")
    inv.add_argument("--q0-tolerance", type=float, default=Q0_TOLERANCE, metavar="TOL",
                     help="stop the contact solve once the rest curvatures are certified within TOL (relative) of "
                          f"the optimum's (default {Q0_TOLERANCE:g}; 0 turns it off; report.json: "
                          "solve.q0_error_bound; docs/solvers.md)")
    inv.add_argument("--strict", action="store_true",
                     help="a contact solve that stops before its tolerances is an error (exit 2, nothing written); "
                          "by default its forces, which lie in their cones and so give an exact equilibrium, are "
                          "written with solve.status 'feasible' and a warning")
    inv.add_argument("--rod-segments", type=int, default=None, metavar="N",
                     help="resolution of the discrete (Cosserat/DER) rest data: N equal segments per strand "
                          "(default: the input's own vertices)")
    inv.add_argument("--stabilize", choices=["stiffness", "report", "none"], default="stiffness",
                     help="stable inversion: 'stiffness' (default) multiplies E and G of exactly the strands that are "
                          "unstable with the contacts that hold them by their certified factor x the margin and "
                          "solves again; 'report' only reports them; 'none' skips the analysis with contacts "
                          "(docs/stability.md)")
    inv.add_argument("--friction-margin", type=float, default=None, metavar="F",
                     help="the contact forces solved stay in the friction cones of (1 - F) mu, so that they stick "
                          "with a margin (default 0.1; 0: forces may lie on the cone boundary, where round-off "
                          "tips them into sliding)")
    inv.add_argument("--stability-margin", type=float, default=None, metavar="M",
                     help="stiffened strands get M x their certified factor (default 1.1)")
    inv.add_argument("--max-stiffness-factor", type=float, default=None, metavar="F",
                     help="no strand is made more than F x stiffer (default 100); strands that would need more "
                          "are named in the report")
    inv.add_argument("--format", action="append", choices=["npz", "obj", "json", "usd", "abc", "vtp", "hair"], default=None,
                     help="output formats (repeatable; default npz, obj, json); rest.npz and report.json are "
                          "always written: check, view, simulate and export read them")
    inv.add_argument("--model", choices=list(MODEL_CHOICES), default="superhelix",
                     help="rod model: superhelix (default; piecewise helices, C1) or clothoid (Super Space Clothoids: "
                          "curvature linear per element and continuous, C2; docs/clothoid.md; every command and exporter "
                          "reads its results)")
    add_material_options(inv)
    inv.add_argument("-q", "--quiet", action="store_true", help="no progress bars and no summary")

    ex = sub.add_parser("example", help="write the bundled example groom (example.obj) and head (head.obj)",
                        epilog="example:\n  groom example ex && groom invert ex/example.obj --head ex/head.obj",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ex.add_argument("directory", nargs="?", default="example", help="where to write them (default ./example)")
    ex.add_argument("--strands", type=int, default=200, help="number of strands (default 200)")
    ex.add_argument("-q", "--quiet", action="store_true", help="no 'wrote ...' line")

    info = sub.add_parser("info", help="print counts, lengths, bounding box, root centroid, the direction strands "
                                       "go and, with --head, how far the roots are from the head",
                          description="What helps spot a wrong --units, --scale or --up before an inversion.",
                          epilog="example:\n  groom info harolongo.data --units cm --head head.obj",
                          formatter_class=argparse.RawDescriptionHelpFormatter)
    info.add_argument("input")
    info.add_argument("--head", default=None, help="head mesh (same units as the input): distance of the roots to it")
    add_input_options(info)
    add_scale_option(info)
    simulate_cmd.add_parsers(sub)
    view_cmd.add_parser(sub)
    export_cmd.add_parser(sub)
    batch_cmd.add_parser(sub, inv)
    return parser


def _load_inputs(args):
    from ..groom import UNIT_SCALE
    from ..io import load_groom, load_head

    factor = getattr(args, "scale", 1.0)
    if not (np.isfinite(factor) and factor > 0):
        raise UserError(f"--scale must be a positive number, got {factor:g}")
    units = UNIT_SCALE[args.units] * factor
    groom = load_groom(args.input, units=units, up=args.up, repair=args.repair,
                       strand_length=args.strand_length)
    head = load_head(args.head, units=units) if getattr(args, "head", None) else None
    return groom, head, UNIT_SCALE[args.units]


def cmd_info(args) -> int:
    groom, head, _ = _load_inputs(args)
    print("\n".join(info_lines(groom, head, args.units, getattr(args, "scale", 1.0))))
    return EXIT_OK


def _vec(v, fmt=".4f") -> str:
    return "[" + " ".join(f"{x:{fmt}}" for x in v) + "]"


def info_lines(groom, head=None, units: str = "m", scale: float = 1.0) -> list[str]:
    """``groom info``: counts, lengths, box, root centroid, the direction strands go, roots to head."""
    from ..groom import up_vector

    lengths = groom.lengths()
    counts = groom.counts
    lo, hi = groom.bounds()
    roots = groom.points[groom.offsets[:-1]]
    tips = groom.points[groom.offsets[1:] - 1]
    d = tips - roots
    norm = np.linalg.norm(d, axis=1)
    unit = d[norm > 0] / norm[norm > 0, None]
    mean = unit.mean(axis=0) if len(unit) else np.zeros(3)
    axis = int(np.argmax(np.abs(mean)))
    signed = ("-" if mean[axis] < 0 else "+") + "xyz"[axis]
    share = float(np.mean(unit[:, axis] * np.sign(mean[axis]) > np.cos(np.pi / 4))) if len(unit) else 0.0
    size = hi - lo
    lines = [f"{groom.source}",
             f"  strands   {groom.n_strands}",
             f"  vertices  {groom.n_points} (per strand min {counts.min()}, median {int(np.median(counts))}, "
             f"max {counts.max()})",
             f"  length    min {lengths.min():.4f} m, median {np.median(lengths):.4f} m, max {lengths.max():.4f} m",
             f"  bounds    {_vec(lo)} .. {_vec(hi)} m, size {_vec(size)} m",
             f"  roots     centroid {_vec(roots.mean(axis=0))} m",
             f"  direction root to tip mostly {signed} (mean unit vector {_vec(mean, '.2f')}; "
             f"{share:.0%} of strands within 45 degrees of {signed})",
             f"  up axis   {groom.up} (gravity {_vec(groom.gravity(), '.2f')} m/s^2)   "
             f"(input units: {args_units(units, scale)}, shown in metres)"]
    hints = []
    up = up_vector(groom.up)
    if len(unit) and float(mean @ up) > 0.5:
        hints.append(f"strands mostly go {signed}, which is up for --up {groom.up}: hair usually hangs down; "
                     "is --up right?")
    if size.max() > 1.0:
        hints.append(f"the groom is {size.max():.2f} m across (a head is about 0.2 m): check --units / --scale")
    elif 0 < size.max() < 0.02:
        hints.append(f"the groom is {size.max() * 1e3:.1f} mm across: check --units / --scale")
    if head is not None:
        from ..contact.head import root_gaps

        gaps = root_gaps(roots, head)
        inside = int(np.count_nonzero(gaps < 0))
        lines.append(f"  head      roots to the surface: median {np.median(np.abs(gaps)) * 1e3:.2f} mm, max "
                     f"{np.abs(gaps).max() * 1e3:.2f} mm; {inside} of {len(gaps)} roots inside the head")
        hlo, hhi = np.asarray(head.bounds)
        lines.append(f"            head bounds {_vec(hlo)} .. {_vec(hhi)} m")
        far = float(np.median(np.abs(gaps)))
        if far > 0.01:
            hints.append(f"the roots are {far * 1e3:.0f} mm from the head (median): are the groom and head in the "
                         "same units and frame? (--snap-roots moves roots onto the head)")
        if inside > len(gaps) // 2:
            hints.append("most roots are inside the head: check the frame, or use --snap-roots")
    lines += [f"  check     {h}" for h in hints]
    return lines


def args_units(units: str, scale: float) -> str:
    return units if scale == 1.0 else f"{units} x {scale:g}"


def cmd_invert(args) -> int:
    from ..invert import SolverFailure, invert_groom
    from ..io.outset import check_target
    from ..io.export import export_formats
    from ..io.results import write_result

    check_target(args.output, inputs=(args.input, args.head))  # before any computation
    try:
        invert_params(args, 1.0)  # option values, before reading the inputs
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    groom, head, scale = _load_inputs(args)
    if head is not None:
        from ..io.head_validation import check_head_fits_groom

        check_head_fits_groom(head, groom)
    if args.contacts == "head" and head is None:
        raise UserError("--contacts head needs --head MESH")
    if head is not None and args.contacts == "none" and not args.quiet:
        print("groom invert: note: --head without --contacts: the head is not an obstacle here; it is used for the "
              f"root gaps{', --snap-roots' if args.snap_roots else ''} and stored with the result "
              "(add --contacts head to hold the strands on it)", file=sys.stderr)
    try:
        params = invert_params(args, scale)
    except ValueError as exc:
        raise UserError(str(exc)) from exc
    if not args.quiet:  # a cold numba cache: compile first, say so once, so the bars measure the work
        from ..warmup import announce_and_warm

        announce_and_warm(params, with_head=head is not None)
    try:
        result = invert_groom(groom, head=head, params=params, quiet=args.quiet)
    except SolverFailure as exc:
        print(f"groom invert: {exc}; nothing was written", file=sys.stderr)
        return EXIT_NOT_CONVERGED
    result.report["input_units"] = args.units
    # rest.npz and report.json always: every other command reads the directory through them
    formats = tuple(dict.fromkeys(("npz", "json") + tuple(args.format))) if args.format else ("npz", "obj", "json")
    extra = [f for f in formats if f in ("usd", "abc", "vtp", "hair")]
    written = write_result(result, args.output, formats=formats,
                           extra=(lambda stage: export_formats(result, stage, extra)) if extra else None)
    if not args.quiet:
        print(summary(result, written))
    return EXIT_OK


def summary(result, written) -> str:
    r = result.report
    kind = "clothoid" if r.get("model") == "clothoid" else "helix"
    lines = [f"groom invert: {r['strands']} strands, {r['elements']} {kind} elements  ({r['input']})",
             f"  fit          max error {r['fit']['max_error_m'] * 1e3:.3f} mm, mean {r['fit']['mean_error_m'] * 1e3:.3f} mm"
             f" (tolerance {r['fit']['tolerance_m'] * 1e3:.3f} mm)"]
    if "contacts" in r:
        c, s = r["contacts"], r["solve"]
        lines.append(f"  contacts     {c['total']} ({c['strand_head']} head, {c['strand_strand']} strand/strand)")
        if "wisp" in r:
            w = r["wisp"]
            lines.append(f"  wisps        radius {w['radius_m'] * 1e3:.2f} mm (the contact radius), about "
                         f"{w['fibres_per_strand']:,.0f} fibres per strand")
        polish = f" + {s['polish_sweeps']} Gauss-Seidel polish sweeps" if s.get("polish_sweeps") else ""
        lines.append(f"  solve        {s['solver']}: {s['status']}, {s['iterations']} iterations{polish}, "
                     f"residual {s['residual']:.2e}, cone violation {s['cone_violation']:.1e} N")
        if s.get("fallback_from"):
            f = s["fallback_from"]
            lines.append(f"               (Gauss-Seidel first: {f['status']} at residual {f['residual']:.1e} after "
                         f"{f['iterations']} sweeps, then clarabel)")
    lines.append(f"  equilibrium  max relative residual {r['equilibrium']['max_relative_residual']:.2e}")
    lines += stability_lines(r["stability"])
    lines += repair_lines(r.get("repairs"))
    if "roots" in r:
        lines.append(f"  roots        {r['roots']['mode']}: median gap {r['roots']['median_gap_m'] * 1e3:.2f} mm, "
                     f"max {r['roots']['max_gap_m'] * 1e3:.2f} mm")
        lines += [f"               {note}" for note in root_notes(r["roots"])]
    lines.append(f"  time         {r['timings_s']['total']:.2f} s   "
                 + ", ".join(f"{k} {v:.2f}" for k, v in r["timings_s"].items() if k != "total"))
    lines.append("  wrote        " + ", ".join(str(p) for p in written))
    return "\n".join(lines)


def _count(n: int, noun: str) -> str:
    """'1 strand', '2 strands'."""
    return f"{n} {noun}" + ("" if n == 1 else "s")


def repair_lines(repairs: dict | None) -> list[str]:
    """What --repair dropped, in input strand indices (rest.npz input_strand maps the output back)."""
    if not repairs:
        return []

    def ids(values):
        shown = ", ".join(str(v) for v in values[:10])
        return shown + (f", ... ({len(values)} in all)" if len(values) > 10 else "")

    dedup, dropped = repairs["deduplicated_strands"], repairs["dropped_strands"]
    lines = [f"  repaired     {_count(repairs['dropped_points'], 'repeated point')} dropped from "
             f"{_count(len(dedup), 'strand')}" + (f" ({ids(dedup)})" if dedup else "")]
    if dropped:
        lines.append(f"               {_count(len(dropped), 'strand')} of fewer than 2 distinct points dropped "
                     f"({ids(dropped)}); rest.npz input_strand maps output strands to input ones")
    return lines


def stability_lines(st: dict) -> list[str]:
    """The summary's stability lines: isolated strands with the input material, then the contacts and the
    stiffening (report.json's stability, docs/outputs.md)."""
    lines = []
    if st["unstable_strands"]:
        lines.append(f"  stability    {_count(st['unstable_strands'], 'strand')} unstable in isolation with the input material "
                     f"(up to {st['required_young_modulus_factor']:.2f}x too soft to stand alone)")
    else:
        lines.append("  stability    every strand is a stable equilibrium on its own")
    stab = st.get("stabilization")
    if stab is None:
        return lines
    if stab["stiffened_strands"]:
        median = stab["median_stiffness_factor_of_stiffened"]
        lines.append(f"  stiffened    {_count(stab['stiffened_strands'], 'strand')} (E and G x{median:.2f} median, "
                     f"x{stab['max_stiffness_factor']:.2f} max) so that the contacts and their stiffness "
                     "hold them: per-strand moduli in rest.npz")
    if stab["unstable_strands"]:
        advice = ("they will move in a simulation" if stab["mode"] == "stiffness"
                  else "--stabilize stiffness would stiffen them")
        lines.append(f"  unstable     {_count(stab['unstable_strands'], 'strand')} even with the contacts that hold them: "
                     f"{advice}")
    elif st["unstable_strands"]:
        lines.append("               every strand is stable with the contacts and stiffness written")
    return lines


def root_notes(roots: dict) -> list[str]:
    """What the root gaps of report.json say to a newcomer: roots inside or far from the head."""
    notes = []
    inside = int(roots.get("inside_head", 0))
    if inside and roots.get("mode") != "snapped":
        notes.append(f"{inside} roots are inside the head (--snap-roots puts them on its surface)")
    if roots.get("median_gap_m", 0.0) > 0.01:
        notes.append("the roots are more than 1 cm from the head (median): are the groom and the head in the same "
                     "units and frame? (groom info INPUT --head MESH)")
    return notes


def cmd_example(args) -> int:
    from ..examples import write_example

    paths = write_example(args.directory, n_strands=args.strands)
    if not args.quiet:
        print("wrote " + ", ".join(str(p) for p in paths))
    return EXIT_OK


COMMANDS = {"invert": cmd_invert, "info": cmd_info, "example": cmd_example,
            "view": view_cmd.cmd_view, "export": export_cmd.cmd_export,
            "simulate": simulate_cmd.cmd_simulate, "check": simulate_cmd.cmd_check, "batch": batch_cmd.cmd_batch}


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    print(f"groom: warning: {message}", file=sys.stderr if file is None else file)


def _join_negative_up(argv: list) -> list:
    """``--up -y`` -> ``--up=-y`` (argparse would take -y for an option)."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] == "--up" and i + 1 < len(argv) and argv[i + 1] in ("-x", "-y", "-z"):
            out.append(f"--up={argv[i + 1]}")
            i += 2
        else:
            out.append(argv[i])
            i += 1
    return out


def main(argv=None) -> int:
    import warnings

    from ..groom import GroomError

    try:
        parser = build_parser()
        args = parser.parse_args(_join_negative_up(sys.argv[1:] if argv is None else list(argv)))
    except KeyboardInterrupt:
        print("groom: interrupted", file=sys.stderr)
        return 130
    previous_showwarning, warnings.showwarning = warnings.showwarning, _one_line_warning
    try:
        return COMMANDS[args.command](args)
    except (GroomError, UserError, FileNotFoundError) as exc:
        print(f"groom {args.command}: error: {cli_message(str(exc))}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"groom {args.command}: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print(f"groom {args.command}: error: out of memory (an input or option too large for this machine)",
              file=sys.stderr)
        return EXIT_USER_ERROR
    except Exception as exc:  # a bug: one line, the traceback only on request
        if os.environ.get("GROOM_DEBUG"):
            raise
        print(f"groom {args.command}: internal error: {type(exc).__name__}: {exc} "
              f"(please report it; GROOM_DEBUG=1 shows the traceback)", file=sys.stderr)
        return EXIT_INTERNAL_ERROR
    finally:
        warnings.showwarning = previous_showwarning


if __name__ == "__main__":
    sys.exit(main())
