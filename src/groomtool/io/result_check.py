"""Checks of a result read back from disk (rest.npz, report.json) before anything uses it.

A tampered, truncated or foreign rest.npz gives a GroomError naming the file and the array, instead
of an IndexError deep in the viewer, a segfault in VTK or NaN written by an export.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..groom import GroomError

MAX_COORDINATE_M = 1e4  # positions beyond 10 km from the origin are not a groom in metres


def _array(arrays, key, source, dtype=np.float64):
    try:
        return np.asarray(arrays[key], dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise GroomError(f"{source}: array {key!r} is not numeric: {exc}") from None


def _shape(a, key, shape, source):
    if a.ndim != len(shape) or any(want is not None and got != want for got, want in zip(a.shape, shape)):
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise GroomError(f"{source}: array {key!r} has shape {a.shape}, expected {want}")


def _finite(a, key, source):
    if a.size and not np.isfinite(a).all():
        k = int(np.argmax(~np.isfinite(a).reshape(-1)))
        raise GroomError(f"{source}: array {key!r} holds a non-finite value at flat index {k}")


def check_result_arrays(arrays: dict, source: str) -> dict:
    """``arrays`` (rest.npz) checked for consistent shapes, finite values and indices in range."""
    offsets = _array(arrays, "strand_offsets", source, np.float64)
    _shape(offsets, "strand_offsets", (None,), source)
    _finite(offsets, "strand_offsets", source)
    if len(offsets) < 2 or offsets[0] != 0 or np.any(np.diff(offsets) < 1) or np.any(offsets != np.round(offsets)):
        raise GroomError(f"{source}: strand_offsets must start at 0 and increase (every strand has an element)")
    n_strands, n_elements = len(offsets) - 1, int(offsets[-1])
    per_element = {"element_lengths": (n_elements,), "curvatures": (n_elements, 3), "rest_curvatures": (n_elements, 3)}
    per_strand = {"root_positions": (n_strands, 3), "root_frames": (n_strands, 3, 3)}
    for key, shape in {**per_element, **per_strand}.items():
        a = _array(arrays, key, source)
        if key.endswith("curvatures") and a.ndim == 1 and a.size == 3 * n_elements:
            a = a.reshape(-1, 3)
        _shape(a, key, shape, source)
        _finite(a, key, source)
    if np.any(_array(arrays, "element_lengths", source) <= 0):
        raise GroomError(f"{source}: array 'element_lengths' holds a length <= 0")
    if np.abs(_array(arrays, "root_positions", source)).max() > MAX_COORDINATE_M:
        raise GroomError(f"{source}: a root lies beyond {MAX_COORDINATE_M:g} m from the origin")
    for key in ("young_modulus", "shear_modulus", "radius", "density"):
        if key in arrays:
            v = _array(arrays, key, source)
            if v.size != 1 or not (0 < float(v.reshape(-1)[0]) < np.inf):
                raise GroomError(f"{source}: {key!r} must be one positive finite number, got {v!r}")
    if "gravity" in arrays:
        g = _array(arrays, "gravity", source)
        _shape(g.reshape(-1), "gravity", (3,), source)
        _finite(g, "gravity", source)
    _check_head(arrays, source)
    _check_contacts(arrays, n_strands, source)
    return arrays


def _check_head(arrays, source):
    v = _array(arrays, "head_vertices", source) if "head_vertices" in arrays else np.zeros((0, 3))
    f = _array(arrays, "head_faces", source, np.float64) if "head_faces" in arrays else np.zeros((0, 3))
    if v.size == 0 and f.size == 0:
        return
    _shape(v, "head_vertices", (None, 3), source)
    _shape(f, "head_faces", (None, 3), source)
    _finite(v, "head_vertices", source)
    _finite(f, "head_faces", source)
    if len(f) and (f.min() < 0 or f.max() >= len(v) or np.any(f != np.round(f))):
        raise GroomError(f"{source}: head_faces refer to vertex {int(f.max())} but there are {len(v)} head vertices")


def _check_contacts(arrays, n_strands, source):
    if "contact_strand_a" not in arrays:
        return
    a = _array(arrays, "contact_strand_a", source)
    _shape(a, "contact_strand_a", (None,), source)
    m = len(a)
    shapes = {"contact_strand_b": (m,), "contact_s_a": (m,), "contact_s_b": (m,), "contact_points": (m, 3),
              "contact_points_b": (m, 3), "contact_normals": (m, 3), "contact_frames": (m, 3, 3),
              "contact_forces": (m, 3)}
    for key, shape in shapes.items():
        if key in arrays:
            x = _array(arrays, key, source)
            _shape(x, key, shape, source)
            if key not in ("contact_s_b",):  # NaN for head contacts
                _finite(x, key, source)
    b = _array(arrays, "contact_strand_b", source) if "contact_strand_b" in arrays else np.zeros(0)
    for key, idx, low in (("contact_strand_a", a, 0), ("contact_strand_b", b, -1)):
        if len(idx) and (idx.min() < low or idx.max() >= n_strands):
            raise GroomError(f"{source}: {key} refers to strand {int(idx.max())} but there are {n_strands} strands")


def read_report(folder) -> dict:
    """report.json of an output directory as a dict ({} when absent); a GroomError when unreadable."""
    path = Path(folder) / "report.json"
    if not path.is_file():
        return {}
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise GroomError(f"{path}: not a readable report: {exc}") from None
    if not isinstance(report, dict):
        raise GroomError(f"{path}: not a report (a JSON object expected, got {type(report).__name__})")
    for key in ("parameters", "contacts", "fit", "solve"):
        if key in report and not isinstance(report[key], dict):
            raise GroomError(f"{path}: {key!r} is not a JSON object")
    return report
