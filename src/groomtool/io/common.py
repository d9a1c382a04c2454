"""Small helpers shared by the readers: unit names to metres, reading a file with clear errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..groom import UNIT_SCALE, GroomError


def unit_scale(units) -> float:
    """Metres per input unit: "m", "cm", "mm" or a positive number (e.g. 0.0254 for inches)."""
    if isinstance(units, str):
        if units not in UNIT_SCALE:
            raise GroomError(f"unknown units {units!r}: use one of {sorted(UNIT_SCALE)} or a number of metres")
        return UNIT_SCALE[units]
    scale = float(units)
    if not np.isfinite(scale) or scale <= 0:
        raise GroomError(f"units must be a positive number of metres per unit, got {units!r}")
    return scale


def check_input(path) -> Path:
    """The path as a Path, or a GroomError if it is missing or not a regular file."""
    path = Path(path)
    if not path.exists():
        raise GroomError(f"{path}: no such file")
    if not path.is_file():
        raise GroomError(f"{path}: not a regular file")
    return path


def read_input(path) -> bytes:
    """The file's bytes; missing or unreadable files raise GroomError naming the path."""
    path = check_input(path)
    try:
        return path.read_bytes()
    except OSError as exc:
        raise GroomError(f"{path}: cannot read: {exc.strerror or exc}") from exc


def strand_of_vertex(offsets: np.ndarray, vertex: int) -> tuple[int, int]:
    """(strand index, vertex index within the strand) of a global vertex index."""
    strand = int(np.searchsorted(offsets, vertex, side="right") - 1)
    return strand, int(vertex - offsets[strand])
