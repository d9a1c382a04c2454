"""Cem Yuksel's ``.hair`` format (cyHair).

A 128-byte little-endian header: "HAIR", uint32 hair count, uint32 point count, uint32 flags
(bit 0 segments array, bit 1 points, bit 2 thickness, bit 3 transparency, bit 4 colour), uint32
default segment count, float32 default thickness, float32 default transparency, float32[3]
default colour, char[88] info.  Then, in this order and only where flagged: uint16 segments per
hair (vertices - 1), float32 xyz points, float32 thickness per point, float32 transparency per
point, float32 rgb colour per point.  Only the points are read; the other arrays are checked and
skipped.  The file must end after the last array.
"""

from __future__ import annotations

import struct

import numpy as np

from ..groom import Groom, GroomError
from .atomic import atomic_write
from .common import read_input, strand_of_vertex
from .validate import validate

_HEADER = struct.Struct("<4sIIIIff3f88s")
SEGMENTS, POINTS, THICKNESS, TRANSPARENCY, COLOUR = 1, 2, 4, 8, 16
_PER_POINT = ((THICKNESS, "thickness", 1), (TRANSPARENCY, "transparency", 1), (COLOUR, "colour", 3))
MAX_SEGMENTS = 0xFFFF


def _cut_point_array(source: str, name: str, got: int, offsets: np.ndarray) -> GroomError:
    strand, vertex = strand_of_vertex(offsets, got)
    n = int(offsets[strand + 1] - offsets[strand])
    return GroomError(
        f"{source}: the file ends inside the {name} array: strand {strand} has {vertex} of its {n} "
        f"vertices ({got} of {offsets[-1]} points)"
    )


def read_hair(path, scale: float = 1.0, up: str = "y", repair: bool = False) -> Groom:
    """Read a cyHair ``.hair`` file; coordinates times ``scale`` give metres."""
    source = str(path)
    data = read_input(path)
    size = len(data)
    if size < _HEADER.size:
        raise GroomError(f"{source}: {size} bytes, shorter than the {_HEADER.size}-byte .hair header")
    signature, n_hairs, n_points, flags, default_segments, *_, info = _HEADER.unpack_from(data)
    if signature != b"HAIR":
        raise GroomError(f"{source}: signature {signature!r}, expected b'HAIR': not a .hair file")
    if not flags & POINTS:
        raise GroomError(f"{source}: the header has no points array (flags {flags:#x}, bit 1 unset)")
    pos = _HEADER.size
    if not flags & SEGMENTS and 12 * n_hairs > size - pos:  # before allocating n_hairs counts
        raise GroomError(f"{source}: the header declares {n_hairs} hairs but the {size - pos} bytes after the "
                         f"header hold at most {(size - pos) // 12} points (every hair has at least one)")

    if flags & SEGMENTS:
        if pos + 2 * n_hairs > size:
            got = (size - pos) // 2
            raise GroomError(
                f"{source}: the file ends inside the segments array: strand {got} has no segment count "
                f"({got} of {n_hairs} hairs)"
            )
        counts = np.frombuffer(data, dtype="<u2", count=n_hairs, offset=pos).astype(np.int64) + 1
        pos += 2 * n_hairs
    else:
        counts = np.full(n_hairs, default_segments + 1, dtype=np.int64)
    if counts.sum() != n_points:
        raise GroomError(
            f"{source}: the header declares {n_points} points but the {n_hairs} hairs' segment counts "
            f"add up to {int(counts.sum())} points"
        )
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)

    if pos + 12 * n_points > size:
        raise _cut_point_array(source, "points", (size - pos) // 12, offsets)
    points = np.frombuffer(data, dtype="<f4", count=3 * n_points, offset=pos).reshape(-1, 3)
    pos += 12 * n_points
    for flag, name, width in _PER_POINT:
        if flags & flag:
            if pos + 4 * width * n_points > size:
                raise _cut_point_array(source, name, (size - pos) // (4 * width), offsets)
            pos += 4 * width * n_points
    if pos != size:
        raise GroomError(f"{source}: {size - pos} trailing bytes after the last array (ends at byte {pos})")

    metadata = {"format": "cyhair", "info": info.split(b"\0", 1)[0].decode("latin-1")}
    groom = Groom(points.astype(np.float64) * scale, offsets, up=up, source=source, metadata=metadata)
    return validate(groom, repair=repair, stored_dtype=np.float32)


def write_hair(groom: Groom, path, scale: float = 1.0) -> None:
    """Write ``groom`` as ``.hair`` (segments + float32 points), coordinates in metres / ``scale``."""
    counts = groom.counts
    bad = np.flatnonzero((counts < 1) | (counts > MAX_SEGMENTS + 1))
    if len(bad):
        raise GroomError(
            f"{groom.source}: strand {bad[0]} has {counts[bad[0]]} vertices; .hair stores 1 to {MAX_SEGMENTS + 1}"
        )
    info = f"groomtool: 1 unit = {scale:g} m, up {groom.up}".encode("ascii")[:87]
    header = _HEADER.pack(
        b"HAIR", groom.n_strands, groom.n_points, SEGMENTS | POINTS, 0, 1.0, 0.0, 1.0, 1.0, 1.0, info
    )
    body = (counts - 1).astype("<u2").tobytes() + (groom.points / scale).astype("<f4").tobytes()
    atomic_write(path, header + body)
