"""``groom export OUTDIR --format usd|abc|vtp|hair|obj``: re-export a result directory from its rest.npz."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..groom import GroomError

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


def default_path(outdir: Path, fmt: str, shape: str) -> Path:
    """Where a format goes without -o: groom.usdc, groom.vtp, rest_shape.<ext> or fitted.<ext>."""
    if fmt in ("usd", "vtp", "abc"):
        return outdir / f"groom.{ {'usd': 'usdc', 'vtp': 'vtp', 'abc': 'abc'}[fmt] }"
    return outdir / f"{'rest_shape' if shape == 'rest' else 'fitted'}.{fmt}"


def export_formats(source, outdir, formats, shape: str | None = None, per_element: int = 8,
                   output=None) -> list[Path]:
    """Write ``formats`` of a result (object, directory or rest.npz) into ``outdir`` (or ``output``,
    for a single format); returns the written paths.  ``shape`` (hair, obj, vtp): "rest" or
    "fitted", default rest for hair/obj and fitted for vtp.  ``groom invert --format`` calls this too."""
    from ..api import export
    from ..io.results import head_mesh, load_arrays

    arrays = load_arrays(source)
    outdir = Path(outdir)
    if output is not None and len(formats) != 1:
        raise GroomError("-o/--output names one file: give a single --format with it")
    written = []
    for fmt in formats:
        if fmt not in FORMATS:
            raise GroomError(f"unknown export format {fmt!r}; use one of {', '.join(FORMATS)}")
        fmt_shape = shape or ("fitted" if fmt == "vtp" else "rest")
        path = Path(output) if output is not None else default_path(outdir, fmt, fmt_shape)
        _check_suffix(path, fmt)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            if fmt == "vtp":  # and the head beside it
                from ..io.vtp import write_vtp

                head_path = path.with_name(f"{path.stem}_head.vtp") if head_mesh(arrays) is not None else None
                written.append(write_vtp(arrays, path, per_element, fmt_shape, head_path=head_path))
                written += [head_path] if head_path is not None else []
            elif fmt == "abc":
                from ..io.alembic import write_alembic

                written.append(write_alembic(arrays, path, per_element))
            else:
                written.append(export(arrays, path, shape=fmt_shape, per_element=per_element))
        except OSError as exc:
            raise GroomError(f"{path}: cannot write: {exc.strerror or exc}") from exc
    return written


def _check_suffix(path: Path, fmt: str) -> None:
    allowed = {"usd": (".usd", ".usda", ".usdc", ".usdz"), "abc": (".abc",), "vtp": (".vtp",), "hair": (".hair",),
               "obj": (".obj",)}
    if path.suffix.lower() not in allowed[fmt]:
        raise GroomError(f"{path}: a {fmt} file must end in {' or '.join(allowed[fmt])}")


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
    p.add_argument("--samples", type=int, default=8, metavar="N", help="samples per helix element (default 8)")
    p.set_defaults(func=cmd_export)
    return p


def cmd_export(args) -> int:
    if args.samples < 1:
        raise GroomError(f"--samples must be >= 1, got {args.samples}")
    source = Path(args.outdir)
    outdir = source if source.is_dir() else source.parent
    formats = list(dict.fromkeys(args.format))
    try:
        written = export_formats(source, outdir, formats, shape=args.shape, per_element=args.samples,
                                 output=args.output)
    except ImportError as exc:
        raise GroomError(f"this format needs an optional dependency (pip install usd-core pyvista vtk): {exc}") from exc
    print("groom export: wrote " + ", ".join(str(p) for p in written))
    return 0
