"""How big a groom file is, from its header or its record counts, without reading the groom.

``peek_counts(path)`` gives ``(strands, vertices)`` of a groom file cheaply: the batch uses them to
estimate what each groom's inversion will cost (``groomtool.batch.estimate_cost``) before any worker
reads it.  Read-only and never raising: a file it cannot size (missing, unreadable, a corrupt header,
a format it does not peek into) gives ``None``, and the caller falls back to the file size.

* ``.data`` (USC-HairSalon): the int32 strand count (4 bytes) and the file size: every strand is an
  int32 vertex count and 12 bytes per vertex, so vertices = (size - 4 - 4 strands) / 12.
* ``.hair`` (cyHair): the 128-byte header's hair and point counts.
* ``.obj``: the ``v`` records and the ``l`` records (one strand per record, as ``save_groom`` writes
  them; files that split strands into one record per segment count segments: an upper bound), by a
  byte scan of the file, no parsing of numbers.  A file of bare vertices has ``strands`` None.
* ``.ply``: the header's ``element vertex N``; ``strands`` None.
* anything else (``.usd*``, ``.abc``): None.
"""

from __future__ import annotations

import os
import re
import struct
from pathlib import Path

_INT = struct.Struct("<i")
_HAIR = struct.Struct("<4sII")  # signature, hairs, points: the start of the 128-byte header
_OBJ_V = re.compile(rb"^[ \t]*v[ \t]", re.MULTILINE)
_OBJ_L = re.compile(rb"^[ \t]*l[ \t]", re.MULTILINE)
_PLY_VERTEX = re.compile(rb"^element[ \t]+vertex[ \t]+(\d+)[ \t]*\r?$", re.MULTILINE)
PLY_HEADER_MAX = 1 << 16  # bytes of a PLY file searched for its header


def peek_counts(path) -> tuple[int | None, int] | None:
    """``(strands, vertices)`` of the groom file ``path`` from its header (``strands`` None where the
    format does not say), or None where it cannot tell (see the module docstring)."""
    path = Path(path)
    suffix = path.suffix.lower()
    peek = _PEEKS.get(suffix)
    if peek is None:
        return None
    try:
        return peek(path)
    except (OSError, ValueError, struct.error):
        return None


def _peek_data(path: Path):
    size = os.stat(path).st_size
    with open(path, "rb") as f:
        head = f.read(4)
    if len(head) < 4:
        return None
    (strands,) = _INT.unpack(head)
    rest = size - 4 - 4 * strands
    if strands < 0 or rest < 0 or rest % 12:
        return None  # not a well-formed .data file: the reader will say why
    return strands, rest // 12


def _peek_hair(path: Path):
    with open(path, "rb") as f:
        head = f.read(_HAIR.size)
    if len(head) < _HAIR.size:
        return None
    signature, hairs, points = _HAIR.unpack(head)
    if signature != b"HAIR":
        return None
    return int(hairs), int(points)


def _peek_obj(path: Path):
    data = path.read_bytes()
    vertices = sum(1 for _ in _OBJ_V.finditer(data))
    lines = sum(1 for _ in _OBJ_L.finditer(data))
    return (lines or None), vertices


def _peek_ply(path: Path):
    with open(path, "rb") as f:
        head = f.read(PLY_HEADER_MAX)
    if not head.startswith(b"ply"):
        return None
    end = head.find(b"end_header")
    m = _PLY_VERTEX.search(head, 0, end if end >= 0 else len(head))
    return (None, int(m.group(1))) if m else None


_PEEKS = {".data": _peek_data, ".hair": _peek_hair, ".obj": _peek_obj, ".ply": _peek_ply}
