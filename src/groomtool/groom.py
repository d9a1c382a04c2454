"""The groom: many strands stored as one ragged array.

A groom is ``points`` (V, 3) float64 in metres and ``offsets`` (S + 1,) int64 such that strand ``i``
is ``points[offsets[i]:offsets[i + 1]]``, root first.  Internally everything is SI in the frame the
data came in (nothing is rotated); ``up`` records which axis points up (x, y, z, -x, -y or -z) so
gravity can be built from it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

UNIT_SCALE = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
UP_AXES = ("y", "z", "x", "-x", "-y", "-z")


def up_vector(up: str) -> np.ndarray:
    """Unit vector of an up axis ("x", "y", "z", "-x", "-y", "-z")."""
    if up not in UP_AXES:
        raise GroomError(f"up axis must be one of {', '.join(UP_AXES)}, got {up!r}")
    v = np.zeros(3)
    v["xyz".index(up[-1])] = -1.0 if up.startswith("-") else 1.0
    return v


class GroomError(ValueError):
    """Bad input data: the message names the file, the strand or line, and what is wrong."""


@dataclass
class Groom:
    """Strands as a ragged array of points (metres).

    points:  (V, 3) float64 vertex positions, strands stored one after the other, root first.
    offsets: (S + 1,) int64, strand i is points[offsets[i]:offsets[i + 1]].
    up:      "y", "z", "x", "-x", "-y" or "-z": the axis pointing away from the ground.
    source:  where the data came from (a path or a description), for messages and reports.
    """

    points: np.ndarray
    offsets: np.ndarray
    up: str = "y"
    source: str = "<memory>"
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64).reshape(-1, 3)
        self.offsets = np.ascontiguousarray(self.offsets, dtype=np.int64)
        if self.up not in UP_AXES:
            raise GroomError(f"{self.source}: up axis must be one of {UP_AXES}, got {self.up!r}")
        if self.offsets.ndim != 1 or self.offsets.size < 1 or self.offsets[0] != 0:
            raise GroomError(f"{self.source}: offsets must start at 0")
        if self.offsets[-1] != len(self.points):
            raise GroomError(
                f"{self.source}: offsets end at {self.offsets[-1]} but there are {len(self.points)} points"
            )
        if np.any(np.diff(self.offsets) < 0):
            raise GroomError(f"{self.source}: offsets must be non-decreasing")

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_strands(cls, strands, up: str = "y", source: str = "<memory>") -> "Groom":
        """Build from a sequence of (n_i, 3) arrays."""
        strands = [np.asarray(s, dtype=np.float64).reshape(-1, 3) for s in strands]
        counts = np.array([len(s) for s in strands], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        points = np.concatenate(strands, axis=0) if strands else np.zeros((0, 3))
        return cls(points=points, offsets=offsets, up=up, source=source)

    # ------------------------------------------------------------------ queries
    @property
    def n_strands(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_points(self) -> int:
        return len(self.points)

    @property
    def counts(self) -> np.ndarray:
        """Vertices per strand, (S,)."""
        return np.diff(self.offsets)

    def strand(self, i: int) -> np.ndarray:
        return self.points[self.offsets[i] : self.offsets[i + 1]]

    def strands(self):
        for i in range(self.n_strands):
            yield self.strand(i)

    @property
    def strand_index(self) -> np.ndarray:
        """Strand id of every vertex, (V,)."""
        return np.repeat(np.arange(self.n_strands), self.counts)

    def segment_lengths(self) -> np.ndarray:
        """Length of every segment, (V - S,), strand after strand."""
        d = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        keep = np.ones(len(d), dtype=bool)
        keep[self.offsets[1:-1] - 1] = False  # drop the jumps between strands
        return d[keep]

    def lengths(self) -> np.ndarray:
        """Polyline length of every strand, (S,)."""
        seg = self.segment_lengths()
        seg_offsets = self.offsets - np.arange(self.n_strands + 1)
        seg_offsets = np.maximum(seg_offsets, 0)
        csum = np.concatenate([[0.0], np.cumsum(seg)])
        return csum[seg_offsets[1:]] - csum[seg_offsets[:-1]]

    def arc_lengths(self) -> np.ndarray:
        """Arc length of every vertex from its strand's root, (V,)."""
        d = np.linalg.norm(np.diff(self.points, axis=0), axis=1)
        d = np.concatenate([[0.0], d])
        d[self.offsets[:-1][self.counts > 0]] = 0.0
        csum = np.cumsum(d)
        start = np.repeat(csum[self.offsets[:-1]], self.counts)
        return csum - start

    def bounds(self) -> np.ndarray:
        """(2, 3) axis-aligned bounding box."""
        if self.n_points == 0:
            return np.zeros((2, 3))
        return np.stack([self.points.min(axis=0), self.points.max(axis=0)])

    def gravity(self, g: float = 9.81) -> np.ndarray:
        """Gravity vector (m/s^2) in this groom's frame: minus ``g`` along the up axis."""
        return up_vector(self.up) * -g + 0.0  # + 0.0: no negative zeros

    def subset(self, strand_ids) -> "Groom":
        strand_ids = np.asarray(strand_ids, dtype=np.int64)
        return Groom.from_strands([self.strand(i) for i in strand_ids], up=self.up, source=self.source)

    def scaled(self, factor: float) -> "Groom":
        """The same groom with every point multiplied by ``factor`` (e.g. 0.01 for a groom read in metres
        that was in centimetres); offsets, up axis, source and metadata kept.  Public API: the package
        itself scales while reading (``units``)."""
        return Groom(self.points * factor, self.offsets.copy(), up=self.up, source=self.source,
                     metadata=dict(self.metadata))

    def __repr__(self) -> str:
        return f"Groom({self.n_strands} strands, {self.n_points} points, up={self.up!r}, source={self.source!r})"
