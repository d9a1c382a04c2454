"""Options, defaults and helpers shared by the ``groom`` sub-commands.

cli/main.py builds the parser and dispatches; every ``*_cmd`` module takes what it shares with the
others from here (never from main), so the command modules import in one direction only.
"""

from __future__ import annotations

import argparse

import numpy as np

from ..fit.fitter import DEFAULT_TOLERANCE_M  # the fit tolerance without --tolerance, whatever --units says
from ..material import Material

EXIT_OK, EXIT_USER_ERROR, EXIT_NOT_CONVERGED = 0, 1, 2
EXIT_INTERNAL_ERROR = 3  # an unexpected exception: a bug, reported in one line (GROOM_DEBUG=1: traceback)
UP_CHOICES = ["x", "y", "z", "-x", "-y", "-z"]
MODEL_CHOICES = ("superhelix", "clothoid")  # groom invert --model
MAX_ROD_SEGMENTS = 10_000  # per strand: beyond, the discrete rest data would not fit in memory


class UserError(Exception):
    """A mistake in the command line or input: printed without a traceback, exit code 1."""


# --------------------------------------------------------------------------------- shared options
def add_input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--units", choices=["m", "cm", "mm"], default="m",
                   help="unit of the input coordinates (and of the head mesh); converted to metres (default m)")
    p.add_argument("--up", choices=UP_CHOICES, default="y", metavar="{x,y,z,-x,-y,-z}",
                   help="the up axis of the input, gravity points the other way (default y; write --up=-y or "
                        "--up -y); nothing is rotated")
    p.add_argument("--repair", action="store_true",
                   help="drop duplicate consecutive points and strands of fewer than 2 points instead of failing")
    p.add_argument("--strand-length", type=int, default=None, metavar="N",
                   help="vertices per strand for OBJ files with vertices only (no 'l' records)")


def add_scale_option(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scale", type=float, default=1.0, metavar="FACTOR",
                   help="multiply the input coordinates (and the head) by FACTOR after --units, e.g. 0.357 for a "
                        "groom reconstructed at 2.8x real size (default 1); tolerances stay in --units")


def add_material_options(p: argparse.ArgumentParser) -> None:
    d = Material()
    p.add_argument("--young", type=float, default=d.young_modulus, help=f"Young's modulus, Pa (default {d.young_modulus:g})")
    p.add_argument("--shear", type=float, default=None, help="shear modulus, Pa (default Young / 3)")
    p.add_argument("--radius", type=float, default=d.radius, help=f"fibre radius, m (default {d.radius:g})")
    p.add_argument("--density", type=float, default=d.density, help=f"density, kg/m^3 (default {d.density:g})")
    p.add_argument("--friction", type=float, default=d.friction, help=f"Coulomb friction coefficient (default {d.friction:g})")


def material_from_args(args) -> Material:
    return Material(young_modulus=args.young, radius=args.radius, density=args.density,
                    friction=args.friction, shear_modulus=args.shear)


# ------------------------------------------------------------------------------- groom invert / batch

def check_invert_options(args) -> None:
    """Option values the computation cannot take, as one-line user errors (before any work)."""
    if args.contact_radius is not None and not (0 < args.contact_radius < np.inf):
        raise UserError(f"--contact-radius must be a positive length, got {args.contact_radius:g}")
    if args.relative_tolerance is not None and not (0 < args.relative_tolerance <= 1):
        raise UserError(f"--relative-tolerance is a fraction of each strand's length: 0 < value <= 1, "
                        f"got {args.relative_tolerance:g}")
    if args.tolerance is not None and not (0 < args.tolerance < np.inf):
        raise UserError(f"--tolerance must be a positive length, got {args.tolerance:g}")
    if args.rod_segments is not None and not (2 <= args.rod_segments <= MAX_ROD_SEGMENTS):
        raise UserError(f"--rod-segments must be 2 to {MAX_ROD_SEGMENTS:,} segments per strand, "
                        f"got {args.rod_segments}")
    if args.gamma is not None and not (0 <= args.gamma < np.inf):
        raise UserError(f"--gamma must be >= 0 and finite, got {args.gamma:g}")
    if not (0 <= args.q0_tolerance < np.inf):
        raise UserError(f"--q0-tolerance must be >= 0 and finite (0: off), got {args.q0_tolerance:g}")
    if args.wisp_radius is not None and not (0 < args.wisp_radius < np.inf):
        raise UserError(f"--wisp-radius must be a positive length, got {args.wisp_radius:g}")
    if args.wisp_radius is not None and args.contact_radius is not None:
        raise UserError("--wisp-radius sets the contact radius: give one of --wisp-radius and --contact-radius")
    if args.friction_margin is not None and not (0 <= args.friction_margin < 1):
        raise UserError(f"--friction-margin must be in [0, 1), got {args.friction_margin:g}")
    if args.stability_margin is not None and not (1 <= args.stability_margin < np.inf):
        raise UserError(f"--stability-margin must be >= 1 and finite, got {args.stability_margin:g}")
    if args.max_stiffness_factor is not None and not (1 <= args.max_stiffness_factor < np.inf):
        raise UserError(f"--max-stiffness-factor must be >= 1 and finite, got {args.max_stiffness_factor:g}")


def invert_params(args, scale):
    from ..invert import InversionParams

    check_invert_options(args)

    return InversionParams(
        material=material_from_args(args), tolerance=DEFAULT_TOLERANCE_M if args.tolerance is None else args.tolerance * scale,
        relative_tolerance=args.relative_tolerance, contacts=args.contacts,
        contact_radius=None if args.contact_radius is None else args.contact_radius * scale,
        wisp_radius=None if args.wisp_radius is None else args.wisp_radius * scale,
        guess=args.guess, solver=args.solver, solver_tolerance=args.solver_tolerance, max_sweeps=args.max_sweeps,
        q0_tolerance=args.q0_tolerance or None, strict=args.strict,
        snap_roots=args.snap_roots, rod_segments=args.rod_segments, stabilize=args.stabilize,
        model=getattr(args, "model", "superhelix"),
        **({} if args.gamma is None else {"gamma": args.gamma}),
        **({} if args.stability_margin is None else {"stability_margin": args.stability_margin}),
        **({} if args.friction_margin is None else {"friction_margin": args.friction_margin}),
        **({} if args.max_stiffness_factor is None else {"max_stiffness_factor": args.max_stiffness_factor}))


# -------------------------------------------------------------------------------------- messages
# library advice -> the command-line flag that does it
CLI_WORDING = (("load with repair=True", "pass --repair"), ("pass strand_length=N", "pass --strand-length N"),
               ("strand_length=", "--strand-length "), ("repair=True", "--repair"))


def cli_message(message: str) -> str:
    """A library error message with its keyword advice replaced by the CLI flags."""
    for old, new in CLI_WORDING:
        message = message.replace(old, new)
    return message
