"""Head (collision) meshes: any triangle mesh trimesh reads (OBJ, PLY, STL, ...), in metres."""

from __future__ import annotations

import numpy as np
import trimesh

from ..groom import GroomError
from .common import check_input, unit_scale


def load_head(path, units="m") -> trimesh.Trimesh:
    """Load a head mesh as one ``trimesh.Trimesh`` scaled to metres (``units``: "m", "cm", "mm" or
    metres per unit).  Scenes are merged into one mesh; no faces or non-finite vertices is an error.
    """
    scale = unit_scale(units)
    path = check_input(path)
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # trimesh raises many types for unreadable or unknown files
        raise GroomError(f"{path}: cannot read as a mesh: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise GroomError(f"{path}: no triangles: not a mesh (a groom of lines, or an empty file?)")
    if not np.isfinite(mesh.vertices).all():
        raise GroomError(f"{path}: the mesh has non-finite vertex coordinates")
    if scale != 1.0:
        mesh.apply_scale(scale)
    mesh.metadata["source"] = str(path)
    return mesh
