"""Input checks every reader runs: finite coordinates, strands of at least two vertices, no
repeated consecutive points.  Problems are GroomErrors naming the file, the strand and the vertex
(0-based, as stored in the file); ``repair=True`` drops what can be dropped and says so in
``metadata["repairs"]``.
"""

from __future__ import annotations

import numpy as np

from ..groom import Groom, GroomError
from .common import strand_of_vertex

REL_TOL = 1e-9  # a segment this much shorter than its strand's bounding box is a repeated point
ULPS = 4  # ... and so is one within this many float ULPs of the strand's coordinates as stored
MAX_COORDINATE_M = 1e4  # a coordinate beyond 10 km is not hair: wrong units or a corrupt file


def _plural(n: int, word: str, plural: str = "") -> str:
    return f"{n} {word}" if n == 1 else f"{n} {plural or word + 's'}"


def _check_finite(groom: Groom) -> None:
    bad = ~np.isfinite(groom.points).all(axis=1)
    if not bad.any():
        return
    first = int(np.argmax(bad))
    strand, vertex = strand_of_vertex(groom.offsets, first)
    n_strands = len(np.unique(groom.strand_index[bad]))
    raise GroomError(
        f"{groom.source}: strand {strand}, vertex {vertex} has a non-finite coordinate "
        f"{tuple(float(x) for x in groom.points[first])} ({_plural(int(bad.sum()), 'such vertex', 'such vertices')} "
        f"in {_plural(n_strands, 'strand')})"
    )


def _check_magnitude(groom: Groom) -> None:
    big = np.abs(groom.points).max(axis=1) > MAX_COORDINATE_M
    if not big.any():
        return
    first = int(np.argmax(big))
    strand, vertex = strand_of_vertex(groom.offsets, first)
    raise GroomError(
        f"{groom.source}: strand {strand}, vertex {vertex} lies {float(np.abs(groom.points[first]).max()):.3g} m "
        f"from the origin (more than {MAX_COORDINATE_M:g} m): not a groom in these units (wrong --units?)"
    )


def _tolerances(groom: Groom, stored_dtype) -> np.ndarray:
    """Per-strand length below which a segment counts as a repeated point."""
    tol = np.zeros(groom.n_strands)
    nonempty = groom.counts > 0
    if not nonempty.any():
        return tol
    starts = groom.offsets[:-1][nonempty]
    pts = groom.points
    size = np.linalg.norm(np.maximum.reduceat(pts, starts) - np.minimum.reduceat(pts, starts), axis=1)
    magnitude = np.maximum.reduceat(np.abs(pts).max(axis=1), starts)
    tol[nonempty] = np.maximum(REL_TOL * size, ULPS * np.finfo(stored_dtype).eps * magnitude)
    return tol


def _repeats(points: np.ndarray, strand_of: np.ndarray, tol: np.ndarray) -> np.ndarray:
    """(V,) True where a vertex lies within its strand's tolerance of the previous vertex."""
    rep = np.zeros(len(points), dtype=bool)
    if len(points) > 1:
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
        same_strand = strand_of[1:] == strand_of[:-1]
        rep[1:] = same_strand & (seg <= tol[strand_of[1:]])
    return rep


def _short_error(groom: Groom, counts: np.ndarray) -> GroomError:
    short = np.flatnonzero(counts < 2)
    first = int(short[0])
    return GroomError(
        f"{groom.source}: strand {first} has {_plural(int(counts[first]), 'vertex', 'vertices')} "
        f"(a strand needs at least 2; {_plural(len(short), 'such strand')}); "
        "load with repair=True to drop them"
    )


def _repeat_error(groom: Groom, rep: np.ndarray, tol: np.ndarray) -> GroomError:
    first = int(np.argmax(rep))
    strand, vertex = strand_of_vertex(groom.offsets, first)
    seg = float(np.linalg.norm(groom.points[first] - groom.points[first - 1]))
    n_strands = len(np.unique(groom.strand_index[rep]))
    return GroomError(
        f"{groom.source}: strand {strand}, vertex {vertex} repeats vertex {vertex - 1} "
        f"(segment {seg:.3g} m, tolerance {tol[strand]:.3g} m; {_plural(int(rep.sum()), 'repeated point')} "
        f"in {_plural(n_strands, 'strand')}); load with repair=True to drop them"
    )


def validate(groom: Groom, repair: bool = False, stored_dtype=np.float64) -> Groom:
    """Check ``groom``; return it (or, with ``repair``, a repaired copy).

    Always errors: no strands, NaN or infinite coordinates, coordinates beyond 10 km (1e4 m).  Errors unless ``repair``:
    strands with fewer than 2 vertices (dropped) and repeated consecutive points, i.e. segments no
    longer than max(1e-9 x the strand's bounding-box diagonal, 4 ULPs of ``stored_dtype`` at the
    strand's coordinate magnitude) (the later point is dropped, then strands left with fewer than
    2 vertices are dropped).  Readers of float32 files pass ``stored_dtype=np.float32``: rounding
    to float32 is noise, not geometry.  Repairs are recorded in ``metadata["repairs"]`` as
    ``{"dropped_points": n, "deduplicated_strands": [...], "dropped_strands": [...]}`` with strand
    indices as in the input.
    """
    if groom.n_strands == 0:
        raise GroomError(f"{groom.source}: contains no strands")
    _check_finite(groom)
    _check_magnitude(groom)
    tol = _tolerances(groom, stored_dtype)
    strand_of = groom.strand_index
    rep = _repeats(groom.points, strand_of, tol)
    if not repair:
        if np.any(groom.counts < 2):
            raise _short_error(groom, groom.counts)
        if rep.any():
            raise _repeat_error(groom, rep, tol)
        return groom

    points, dropped_from = groom.points, []
    while rep.any():  # dropping a point can leave its neighbours within tolerance: repeat
        dropped_from.append(strand_of[rep])
        points, strand_of = points[~rep], strand_of[~rep]
        rep = _repeats(points, strand_of, tol)
    counts = np.bincount(strand_of, minlength=groom.n_strands)
    short = np.flatnonzero(counts < 2)
    if len(short) == 0 and not dropped_from:
        return groom
    if len(short) == groom.n_strands:
        raise GroomError(f"{groom.source}: no strand has 2 distinct vertices, nothing left after repair")
    keep = np.isin(strand_of, short, invert=True)
    dropped_from = np.concatenate(dropped_from) if dropped_from else np.zeros(0, dtype=np.int64)
    repairs = {
        "dropped_points": int(len(dropped_from)),
        "deduplicated_strands": [int(i) for i in np.unique(dropped_from)],
        "dropped_strands": [int(i) for i in short],
    }
    kept_counts = np.delete(counts, short)
    offsets = np.concatenate([[0], np.cumsum(kept_counts)])
    metadata = dict(groom.metadata, repairs=repairs)
    return Groom(points[keep], offsets, up=groom.up, source=groom.source, metadata=metadata)
