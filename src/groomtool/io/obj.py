"""Wavefront OBJ polylines: ``v`` vertices and ``l`` records (one strand per chain of records).

``l`` records may list many vertices (``l 1 2 3``), use negative (relative) indices and
``v/vt`` pairs, and may be split one segment per record (``l 1 2`` then ``l 2 3``): records that
share an end vertex join into one strand.  A file of bare ``v`` records is split into strands of
``strand_length`` vertices.  Other records (``vn``, ``vt``, ``o``, ``g``, comments) are ignored.
"""

from __future__ import annotations

import numpy as np

from ..groom import Groom, GroomError
from .atomic import atomic_open
from .chain import chain_segments, split_fixed
from .common import read_input
from .validate import validate


_V, _L, _F = ("v ", "v\t"), ("l ", "l\t"), ("f ", "f\t")


def _lines(text: str) -> list[str]:
    """Stripped lines; a line ending in a backslash continues on the next (numbering is kept)."""
    lines = [line.strip() for line in text.splitlines()]
    if "\\" not in text:
        return lines
    for i in range(len(lines) - 1):
        if lines[i].endswith("\\"):
            lines[i + 1] = lines[i][:-1] + " " + lines[i + 1]
            lines[i] = ""
    return lines


def _vertex_coordinates(lines: list[str], at: list[int], source: str) -> np.ndarray:
    """x, y, z of every ``v`` record; more numbers (w, or r g b colours) are ignored, fewer are an error."""
    rows = [lines[i][2:].split() for i in at]
    widths = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    short = np.flatnonzero(widths < 3)
    if len(short):
        i = at[int(short[0])]
        raise GroomError(f"{source}: line {i + 1}: a v record needs 3 numbers, got {lines[i]!r}")
    if len(rows) and np.any(widths != 3):
        rows = [r[:3] for r in rows]
    try:
        return np.array(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError:
        pass  # find the bad line below
    for row, i in zip(rows, at):
        try:
            [float(x) for x in row]
        except ValueError:
            raise GroomError(f"{source}: line {i + 1}: a v record needs 3 numbers, got {lines[i]!r}") from None
    raise GroomError(f"{source}: a v record holds a value that is not a number")


def _raw_indices(records: list[list[str]], at: list[int], source: str) -> np.ndarray:
    tokens = [t.partition("/")[0] for r in records for t in r]
    try:
        return np.array(tokens, dtype=np.int64)
    except (ValueError, OverflowError):
        for r, i in zip(records, at):
            for t in r:
                try:
                    np.int64(int(t.partition("/")[0]))
                except (ValueError, OverflowError):
                    raise GroomError(f"{source}: line {i + 1}: bad vertex index {t!r} in l record") from None
        raise


def _line_segments(lines: list[str], l_at: list[int], v_at: list[int], source: str):
    """(starts, ends, record of each segment) as 0-based vertex ids, from the ``l`` records."""
    records = [lines[i].split()[1:] for i in l_at]
    raw = _raw_indices(records, l_at, source)
    record_of = np.repeat(np.arange(len(records)), [len(r) for r in records])
    line_of = np.asarray(l_at)[record_of] + 1
    n_vertices = len(v_at)
    defined = np.searchsorted(np.asarray(v_at, dtype=np.int64), np.asarray(l_at))[record_of]  # v before the l
    checks = (
        (raw == 0, lambda k: "vertex index 0 (OBJ indices start at 1)"),
        ((raw < 0) & (raw + defined < 0),
         lambda k: f"relative index {raw[k]} points before the first vertex ({defined[k]} defined so far)"),
        (raw > n_vertices, lambda k: f"vertex index {raw[k]} but the file has {n_vertices} vertices"),
    )
    for bad, message in checks:
        if bad.any():
            k = int(np.argmax(bad))
            raise GroomError(f"{source}: line {line_of[k]}: {message(k)}")
    flat = np.where(raw < 0, raw + defined, raw - 1)
    repeat = np.zeros(len(flat), dtype=bool)  # l 4 5 5 6: the same point twice, collapse it
    repeat[1:] = (record_of[1:] == record_of[:-1]) & (flat[1:] == flat[:-1])
    flat, record_of = flat[~repeat], record_of[~repeat]
    short = np.bincount(record_of, minlength=len(records)) < 2
    if short.any():
        i = l_at[int(np.argmax(short))]
        raise GroomError(f"{source}: line {i + 1}: an l record needs at least 2 distinct vertices, got {lines[i]!r}")
    inside = record_of[1:] == record_of[:-1]
    return flat[:-1][inside], flat[1:][inside], record_of[1:][inside]


def read_obj(path, scale: float = 1.0, up: str = "y", repair: bool = False, strand_length=None) -> Groom:
    """Read OBJ polylines; coordinates times ``scale`` give metres.

    ``strand_length`` (vertices per strand) is used only when the file has no ``l`` records.
    """
    source = str(path)
    lines = _lines(read_input(path).decode("utf-8", errors="replace"))
    v_at = [i for i, line in enumerate(lines) if line.startswith(_V)]
    l_at = [i for i, line in enumerate(lines) if line.startswith(_L)]
    coords = _vertex_coordinates(lines, v_at, source)
    n_vertices = len(coords)

    if l_at:
        starts, ends, record = _line_segments(lines, l_at, v_at, source)
        order, offsets = chain_segments(
            starts, ends, n_vertices, lambda k: f"line {l_at[record[k]] + 1}", source, base=1
        )
        points = coords[order]
    elif n_vertices and strand_length is not None:
        offsets, points = split_fixed(n_vertices, strand_length, source), coords
    elif any(line.startswith(_F) for line in lines):
        n_faces = sum(line.startswith(_F) for line in lines)
        raise GroomError(f"{source}: has {n_faces} faces but no l polylines: a mesh, not a groom (a head?)")
    elif n_vertices:
        raise GroomError(
            f"{source}: has {n_vertices} vertices but no l polylines: pass strand_length=N "
            "(vertices per strand) to split them into strands"
        )
    else:
        raise GroomError(f"{source}: no vertices")
    groom = Groom(points * scale, offsets, up=up, source=source, metadata={"format": "obj"})
    return validate(groom, repair=repair)


def write_obj(groom: Groom, path, scale: float = 1.0) -> None:
    """Write ``groom`` as OBJ ``v`` + one ``l`` polyline per strand, coordinates in metres / ``scale``."""
    counts = groom.counts
    if np.any(counts < 2):
        i = int(np.argmax(counts < 2))
        raise GroomError(f"{groom.source}: strand {i} has {counts[i]} vertices, an OBJ l record needs 2")
    header = f"# groomtool: {groom.n_strands} strands, {groom.n_points} vertices, 1 unit = {scale:g} m, up {groom.up}\n"
    with atomic_open(path, "w", encoding="ascii", newline="\n") as f:
        f.write(header)
        x, y, z = (groom.points / scale).T.tolist()
        if groom.n_points:  # str.format over lists: about twice as fast as np.savetxt
            f.write("\n".join(map("v {:.9g} {:.9g} {:.9g}".format, x, y, z)) + "\n")
        for start, stop in zip(groom.offsets[:-1] + 1, groom.offsets[1:] + 1):
            f.write("l " + " ".join(map(str, range(start, stop))) + "\n")
