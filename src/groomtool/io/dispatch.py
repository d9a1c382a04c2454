"""``load_groom`` / ``save_groom``: pick the reader or writer from the file extension (formats.py's table)."""

from __future__ import annotations

from pathlib import Path

from ..groom import Groom, GroomError
from .common import check_input, unit_scale
from .formats import FORMATS
from .hair import read_hair, write_hair
from .obj import read_obj, write_obj
from .ply import read_ply
from .usc import read_data, write_data


def _read_usd(path, scale, up, repair):
    """Hook: ``groomtool.io.usd.read_usd(path, scale=, up=, repair=)`` when usd-core is installed."""
    try:
        from . import usd
    except ModuleNotFoundError as exc:
        if exc.name and (exc.name == "pxr" or exc.name.startswith("pxr.") or exc.name == f"{__package__}.usd"):
            raise GroomError(f"{path}: USD support needs usd-core (pip install usd-core)") from exc
        raise
    return usd.read_usd(path, scale=scale, up=up, repair=repair)


def _read_alembic(path, scale, up, repair):
    """Hook: ``groomtool.io.alembic.read_alembic`` (needs the optional alembic3d package; says so)."""
    from .alembic import read_alembic

    return read_alembic(path, scale=scale, up=up, repair=repair)


# the readers and writers of grooms by format name; by suffix from formats.FORMATS
READER_OF = {"usd": _read_usd, "abc": _read_alembic, "hair": read_hair, "obj": read_obj, "data": read_data,
             "ply": read_ply}
WRITER_OF = {"hair": write_hair, "obj": write_obj, "data": write_data}
READERS = {suffix: READER_OF[f.name] for f in FORMATS if f.reads for suffix in f.suffixes}
WRITERS = {suffix: WRITER_OF[f.name] for f in FORMATS if f.writes for suffix in f.suffixes}
SPLITTABLE = tuple(suffix for f in FORMATS if f.splittable for suffix in f.suffixes)  # strand_length applies


def load_groom(path, units="m", up: str = "y", repair: bool = False, strand_length=None) -> Groom:
    """Read a groom (.obj, .ply, .data, .hair; .usd* with usd-core; .abc with alembic3d) into metres, validated.

    units: "m", "cm", "mm" or metres per file unit.  up: the file's up axis, "y" or "z".
    repair: drop strands with < 2 vertices and repeated points instead of failing (recorded in
    ``metadata["repairs"]``).  strand_length: vertices per strand for OBJ/PLY files without lines.
    """
    scale = unit_scale(units)
    suffix = Path(path).suffix.lower()
    if suffix not in READERS:
        raise GroomError(f"{path}: unknown groom format {suffix!r}; readable: {', '.join(sorted(READERS))}")
    check_input(path)
    options = {"strand_length": strand_length} if suffix in SPLITTABLE else {}
    return READERS[suffix](path, scale=scale, up=up, repair=repair, **options)


def save_groom(groom: Groom, path, units="m") -> Path:
    """Write ``groom`` atomically as .obj, .data or .hair, coordinates in ``units``; returns the path."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITERS:
        raise GroomError(f"{path}: cannot write {suffix!r}; writable: {', '.join(sorted(WRITERS))}")
    WRITERS[suffix](groom, path, scale=unit_scale(units))
    return path
