"""``groom export OUTDIR --format usd|abc|vtp|hair|obj``: re-export a result directory from its rest.npz."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..groom import GroomError

# io.export.FORMATS (tests/test_api.py checks they agree), spelled out so that the parser does not import io
FORMATS = ("usd", "abc", "vtp", "hair", "obj")

EPILOG = """examples:
  groom export out --format usd                    out/groom.usdc: strands, rest data, head (docs/usd.md)
  groom export out --format usd -o groom.usda      text USD
  groom export out --format abc                    out/groom.abc: Alembic, cm, Unreal's groom_* attributes
                                                   (needs: pip install 'groomtool[alembic]')
  groom export out --format vtp                    out/groom.vtp (+ out/groom_head.vtp) for ParaView
  groom export out --format hair --shape fitted    out/fitted.hair
  groom export out --format obj --format hair      out/rest_shape.obj and out/rest_shape.hair

exit codes: 0 ok, 1 user error (no rest.npz, unwritable output, bad option)
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "export", help="re-export a result directory (rest.npz) as USD, Alembic, VTP, .hair or OBJ",
        description="Write other formats of an existing 'groom invert' output directory, from its rest.npz.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("outdir", help="output directory of 'groom invert' (or its rest.npz)")
    p.add_argument("--format", action="append", choices=FORMATS, required=True,
                   help="format to write (repeatable): usd (groom + rest data for simulators), abc (Alembic groom "
                        "for Unreal/Maya/Houdini, cm), vtp (ParaView), "
                        "hair, obj (the rest or fitted polylines)")
    p.add_argument("-o", "--output", default=None,
                   help="output file (one --format only; default in OUTDIR: groom.usdc, groom.abc, groom.vtp, "
                        "rest_shape.hair, ...)")
    p.add_argument("--shape", choices=["rest", "fitted"], default=None,
                   help="polylines of hair/obj (default rest) and points of the vtp (default fitted); usd holds both")
    p.add_argument("--samples", type=int, default=8, metavar="N", help="samples per rod element, helix or clothoid (default 8)")
    p.set_defaults(func=cmd_export)
    return p


def cmd_export(args) -> int:
    if args.samples < 1:
        raise GroomError(f"--samples must be >= 1, got {args.samples}")
    source = Path(args.outdir)
    outdir = source if source.is_dir() else source.parent
    from ..io.export import export_formats  # io (numpy, the readers): kept off the CLI's start

    formats = list(dict.fromkeys(args.format))
    written = export_formats(source, outdir, formats, shape=args.shape, per_element=args.samples, output=args.output)
    print("groom export: wrote " + ", ".join(str(p) for p in written))
    return 0
