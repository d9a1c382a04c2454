"""USC-HairSalon ``.data``: little-endian int32 strand count, then per strand an int32 vertex count
and that many float32 x, y, z.  The file ends exactly after the last strand.
"""

from __future__ import annotations

import struct

import numpy as np

from ..groom import Groom, GroomError
from .atomic import atomic_write
from .common import read_input
from .validate import validate

_INT = struct.Struct("<i")


def _strand_counts(data: bytes, source: str) -> np.ndarray:
    """Vertex count of every strand, checking the file ends exactly after the last one."""
    size = len(data)
    if size < 4:
        raise GroomError(f"{source}: {size} bytes, too short for the 4-byte strand count")
    (n_strands,) = _INT.unpack_from(data, 0)
    if n_strands < 0:
        raise GroomError(f"{source}: negative strand count {n_strands}: not a USC .data file?")
    if 4 * n_strands > size - 4:  # each strand has its vertex count at least
        raise GroomError(f"{source}: {n_strands} strands declared but the file ({size} bytes) ends before the "
                         f"vertex count of strand {(size - 4) // 4} at the latest: corrupt, or not a USC .data file")
    counts = np.empty(n_strands, dtype=np.int64)
    pos = 4
    for i in range(n_strands):
        if pos + 4 > size:
            raise GroomError(
                f"{source}: strand {i}: the file ends (at byte {size}) before its vertex count; "
                f"{n_strands} strands declared"
            )
        (count,) = _INT.unpack_from(data, pos)
        pos += 4
        if count < 0:
            raise GroomError(f"{source}: strand {i} declares a negative vertex count ({count}) at byte {pos - 4}")
        if pos + 12 * count > size:
            raise GroomError(
                f"{source}: strand {i} declares {count} vertices but the file ends after {(size - pos) // 12} "
                f"({n_strands} strands declared, file is {size} bytes)"
            )
        counts[i] = count
        pos += 12 * count
    if pos != size:
        last = f"strand {n_strands - 1}" if n_strands else "the strand count"
        raise GroomError(
            f"{source}: {size - pos} trailing bytes after the last strand ({last} ends at byte {pos}); "
            "corrupt, or not a USC .data file"
        )
    return counts


def read_data(path, scale: float = 1.0, up: str = "y", repair: bool = False) -> Groom:
    """Read a USC-HairSalon ``.data`` file; coordinates times ``scale`` give metres."""
    source = str(path)
    data = read_input(path)
    counts = _strand_counts(data, source)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    words = np.frombuffer(data, dtype="<f4")  # the checks above make the size a multiple of 4
    is_point = np.ones(len(words), dtype=bool)
    is_point[0] = False
    is_point[1 + np.arange(len(counts)) + 3 * offsets[:-1]] = False  # the per-strand counts
    points = words[is_point].reshape(-1, 3).astype(np.float64) * scale
    groom = Groom(points, offsets, up=up, source=source, metadata={"format": "usc-data"})
    return validate(groom, repair=repair, stored_dtype=np.float32)


def write_data(groom: Groom, path, scale: float = 1.0) -> None:
    """Write ``groom`` as USC ``.data`` (float32), coordinates in metres / ``scale``."""
    counts = groom.counts
    words = np.empty(1 + groom.n_strands + 3 * groom.n_points, dtype="<i4")
    words[0] = groom.n_strands
    count_at = 1 + np.arange(groom.n_strands) + 3 * groom.offsets[:-1]
    words[count_at] = counts
    is_point = np.ones(len(words), dtype=bool)
    is_point[0] = False
    is_point[count_at] = False
    words.view("<f4")[is_point] = (groom.points / scale).ravel()
    atomic_write(path, words.tobytes())
