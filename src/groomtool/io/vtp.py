"""VTK PolyData (.vtp, for ParaView and the viewer): one polyline per strand with the result's fields.

Point data (per sample) and cell data (per strand) are listed in docs/outputs.md; field data hold
the material constants (and ``model`` for a Super Space Clothoid result).  The strands are the
fitted rods -- Super-Helices or clothoids -- (or the rest shape) sampled ``per_element`` times per
element; ``rest_displacement`` (rest - fitted, per point) lets ParaView's "Warp By Vector" blend from
the groomed to the rest shape.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..groom import GroomError
from . import fields
from .atomic import atomic_path
from .formats import suffixes
from .results import head_mesh, load_arrays

SHAPES = ("fitted", "rest")
MATERIAL_KEYS = ("young_modulus", "shear_modulus", "radius", "density", "friction", "gravity")


def lines_connectivity(offsets: np.ndarray) -> np.ndarray:
    """VTK cell array [n0, i..., n1, j..., ...] with one polyline per strand."""
    offsets = np.asarray(offsets, dtype=np.int64)
    counts = np.diff(offsets)
    out = np.empty(len(counts) + offsets[-1], dtype=np.int64)
    starts = offsets[:-1] + np.arange(len(counts))
    out[starts] = counts
    keep = np.ones(len(out), dtype=bool)
    keep[starts] = False
    out[keep] = np.arange(offsets[-1])
    return out


def strands_polydata(source, per_element: int = 8, shape: str = "fitted"):
    """A ``pyvista.PolyData`` of the strands with every point, cell and field array."""
    import pyvista as pv

    if shape not in SHAPES:
        raise GroomError(f"shape must be one of {SHAPES}, got {shape!r}")
    arrays = load_arrays(source)
    samples = fields.sample(arrays, per_element)
    points = samples.points if shape == "fitted" else samples.rest_points
    poly = pv.PolyData(np.ascontiguousarray(points), lines=lines_connectivity(samples.offsets))
    for name, value in fields.vertex_fields(arrays, samples).items():
        poly.point_data[name] = value
    for name, value in fields.strand_fields(arrays).items():
        poly.cell_data[name] = value
    for name in MATERIAL_KEYS:
        if name in arrays:
            poly.field_data[name] = np.atleast_1d(np.asarray(arrays[name], dtype=np.float64))
    poly.field_data["shape"] = np.array([shape])
    if samples.model == "clothoid":  # absent for Super-Helices (their files are as before)
        poly.field_data["model"] = np.array([samples.model])
    return poly


def head_polydata(source, head=None):
    """The result's head mesh (else the trimesh ``head``) as ``pyvista.PolyData``, or None."""
    import pyvista as pv

    mesh = head_mesh(load_arrays(source))
    if mesh is None and head is not None:
        mesh = (np.asarray(head.vertices, dtype=np.float64), np.asarray(head.faces, dtype=np.int64))
    if mesh is None:
        return None
    vertices, faces = mesh
    return pv.PolyData(vertices, np.column_stack([np.full(len(faces), 3), faces]).ravel())


def write_vtp(source, path, per_element: int = 8, shape: str = "fitted", head_path=None) -> Path:
    """Write the strands of a result (object, output directory, rest.npz or arrays) as .vtp.

    ``shape``: "fitted" (the groomed shape) or "rest".  ``head_path``: also write the head mesh
    there (.vtp), when the result has one.  Binary XML, written atomically; returns the path.
    """
    path = Path(path)
    if path.suffix.lower() not in suffixes("vtp"):
        raise GroomError(f"{path}: VTK PolyData files end in .vtp")
    arrays = load_arrays(source)
    poly = strands_polydata(arrays, per_element, shape)
    with atomic_path(path) as tmp:
        poly.save(tmp, binary=True)
    if head_path is not None:
        head = head_polydata(arrays)
        if head is not None:
            with atomic_path(Path(head_path)) as tmp:
                head.save(tmp, binary=True)
    return path
