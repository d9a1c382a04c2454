"""A result in the export formats: which formats and suffixes there are, where each goes by default,
and the writer each takes.  ``groom export``, ``groom invert --format`` and ``groom batch --format``
call :func:`export_formats`; the Python API's ``groomtool.export`` calls :func:`export_path`.
"""

from __future__ import annotations

from pathlib import Path

from ..groom import Groom, GroomError
from . import fields
from .dispatch import save_groom
from .results import head_mesh, load_arrays, up_axis

SUFFIXES = {"usd": (".usd", ".usda", ".usdc", ".usdz"), "abc": (".abc",), "vtp": (".vtp",), "hair": (".hair",),
            "obj": (".obj",)}  #: the formats of export_formats and the suffixes each may be written with
FORMATS = tuple(SUFFIXES)
EXPORT_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz", ".vtp", ".obj", ".hair", ".data")  #: those of export_path


def export_path(result, path, shape: str = "rest", per_element: int = 8) -> Path:
    """:func:`groomtool.export`: ``result`` written to ``path`` by its extension; returns the path."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EXPORT_SUFFIXES:
        raise GroomError(f"{path}: cannot export {suffix!r}; use one of {', '.join(EXPORT_SUFFIXES)}")
    if shape not in ("rest", "fitted"):
        raise GroomError(f"shape must be 'rest' or 'fitted', got {shape!r}")
    if suffix.startswith(".usd"):
        from .usd import write_usd

        return write_usd(result, path, per_element=per_element)
    if suffix == ".vtp":
        from .vtp import write_vtp

        return write_vtp(result, path, per_element=per_element, shape=shape)

    arrays = load_arrays(result)
    samples = fields.sample(arrays, per_element)
    points = samples.rest_points if shape == "rest" else samples.points
    groom = Groom(points, samples.offsets, up=up_axis(arrays), source=f"{shape} shape")
    return save_groom(groom, path)


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
                from .vtp import write_vtp

                head_path = path.with_name(f"{path.stem}_head.vtp") if head_mesh(arrays) is not None else None
                written.append(write_vtp(arrays, path, per_element, fmt_shape, head_path=head_path))
                written += [head_path] if head_path is not None else []
            elif fmt == "abc":
                from .alembic import write_alembic

                written.append(write_alembic(arrays, path, per_element))
            else:
                written.append(export_path(arrays, path, shape=fmt_shape, per_element=per_element))
        except OSError as exc:
            raise GroomError(f"{path}: cannot write: {exc.strerror or exc}") from exc
    return written


def _check_suffix(path: Path, fmt: str) -> None:
    if path.suffix.lower() not in SUFFIXES[fmt]:
        raise GroomError(f"{path}: a {fmt} file must end in {' or '.join(SUFFIXES[fmt])}")
