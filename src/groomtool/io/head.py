"""Head (collision) meshes: any triangle mesh trimesh reads (OBJ, PLY, STL, ...), in metres."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..groom import GroomError
from .common import check_input, unit_scale
from .head_validation import validate_head

if TYPE_CHECKING:
    import trimesh


def load_head(path, units="m") -> trimesh.Trimesh:
    """Load a head mesh as one ``trimesh.Trimesh`` scaled to metres (``units``: "m", "cm", "mm" or
    metres per unit).  Scenes are merged into one mesh.  Checked by ``validate_head``: no faces,
    non-finite vertices, absurd coordinates or only degenerate faces are errors; faces wound against
    their neighbours are reversed with a ``HeadWarning``.
    """
    import trimesh  # 1.5 s with scipy.spatial: kept off the CLI's start (groomtool.io is imported there)

    scale = unit_scale(units)
    path = check_input(path)
    try:
        raw = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable or unknown files
        raise GroomError(f"{path}: cannot read as a mesh: {exc}") from exc
    if not isinstance(raw, trimesh.Trimesh) or len(raw.faces) == 0:
        raise GroomError(f"{path}: no triangles: not a mesh (a groom of lines, or an empty file?)")
    vertices = np.asarray(raw.vertices, dtype=np.float64) * scale
    validate_head(vertices, raw.faces, str(path))  # NaN and index checks before trimesh merges vertices
    merged = trimesh.Trimesh(vertices, raw.faces, process=True)
    vertices, faces = validate_head(merged.vertices, merged.faces, str(path))
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.metadata["source"] = str(path)
    return mesh
