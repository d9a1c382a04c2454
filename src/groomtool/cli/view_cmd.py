"""``groom view OUTDIR``: look at a result in a pyvista window, or render it to a PNG off-screen."""

from __future__ import annotations

import argparse

from ..groom import GroomError

EPILOG = """examples:
  groom view out                                   interactive window (needs a display)
  groom view out --color contact-force             colour by the contact force at each vertex
  groom view out --rest --screenshot rest.png      render the rest shape off-screen (no display needed)
  groom view out --screenshot shot.png --size 1600 1200
  groom view out --head head.obj --units cm        a head for results saved without one

colours: curvature-change |q0 - q| (1/m), contact-force (uN), stability margin 1 - rho
(< 0: the strand cannot stand alone), fit-error of the strand (mm)
keys: t rest/groomed shape, c contacts on/off, h head on/off (also check boxes, bottom left)
exit codes: 0 ok, 1 user error (no rest.npz, bad option, no display without --screenshot)
"""



def add_parser(subparsers) -> argparse.ArgumentParser:
    from ..viz.viewer import COLORS  # no pyvista import at this point

    p = subparsers.add_parser(
        "view", help="show a result: head, strands coloured by a field, contact forces",
        description="Show the result of 'groom invert' (its rest.npz) in a 3D window, or render it to a PNG.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("outdir", help="output directory of 'groom invert' (or its rest.npz)")
    p.add_argument("--color", choices=list(COLORS), default="curvature-change",
                   help="what colours the strands (default curvature-change)")
    p.add_argument("--rest", action="store_true", help="start on the rest shape instead of the groomed shape")
    p.add_argument("--screenshot", metavar="FILE.png", default=None,
                   help="render off-screen into this PNG and exit (works without a display)")
    p.add_argument("--size", nargs=2, type=int, metavar=("W", "H"), default=[1280, 960],
                   help="window / screenshot size in pixels (default 1280 960)")
    p.add_argument("--head", default=None, help="head mesh to show when rest.npz holds none")
    p.add_argument("--units", choices=["m", "cm", "mm"], default="m", help="unit of --head (default m)")
    p.add_argument("--samples", type=int, default=8, metavar="N",
                   help="samples per helix element for drawing (default 8)")
    p.set_defaults(func=cmd_view)
    return p


def cmd_view(args) -> int:
    w, h = args.size
    if not (16 <= w <= 16384 and 16 <= h <= 16384):
        raise GroomError(f"--size {w} {h}: width and height must be 16 to 16384 pixels")
    if args.samples < 1:
        raise GroomError(f"--samples must be >= 1, got {args.samples}")
    from ..viz import viewer  # pyvista and vtk (hard dependencies, about 1 s): kept off the CLI's start
    head = None
    if args.head:
        from ..io import load_head

        head = load_head(args.head, units=args.units)
    options = dict(color=args.color, rest=args.rest, head=head, per_element=args.samples)
    if args.screenshot:
        path = viewer.screenshot(args.outdir, args.screenshot, size=(w, h), **options)
        print(f"groom view: wrote {path} ({w}x{h})")
    else:
        viewer.show(args.outdir, size=(w, h), **options)
    return 0
