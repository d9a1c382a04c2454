"""Write an inversion result into an output directory: rest.npz, rest_shape.obj, fitted.obj, report.json.

The directory is one atomic set (io/outset.py): all files are written into a staging directory and
swapped in together, so the directory holds the old complete set or the new one, never a mix, and
no stale output of an earlier run.  The schema of rest.npz is documented in docs/outputs.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..groom import Groom, GroomError
from .atomic import atomic_open
from .outset import output_set

NPZ_SCHEMA_VERSION = 1


def result_arrays(result) -> dict:
    """The arrays of rest.npz (flat, unpadded, SI units)."""
    helix = result.helix
    mat = result.material
    flat_offsets = helix.flat_offsets()
    arrays = {
        "schema_version": np.array(NPZ_SCHEMA_VERSION),
        "strand_offsets": flat_offsets,
        "element_lengths": helix.to_flat(helix.lengths),
        "root_positions": helix.root_positions,
        "root_frames": helix.root_frames,
        "curvatures": helix.to_flat(helix.curvatures),
        "rest_curvatures": helix.to_flat(result.rest_curvatures),
        "fit_max_error": result.fit_max_error,
        "stiffness_ratio": np.zeros(0),
        "young_modulus": np.array(mat.young_modulus),
        "shear_modulus": np.array(mat.G),
        "radius": np.array(mat.radius),
        "density": np.array(mat.density),
        "friction": np.array(mat.friction),
        "gravity": np.asarray(result.gravity, dtype=np.float64),
    }
    factor = getattr(result, "stiffness_factor", None)
    factor = np.ones(helix.n_strands) if factor is None else np.asarray(factor, dtype=np.float64)
    held = getattr(result, "held_ratio", None)
    # per strand: the stable inversion may stiffen strands (stabilize.py); the ratios are relative to the moduli
    # written (a ratio rho with the input material is rho / f_s with E_s = f_s E): < 1 is stable
    arrays.update({
        "stiffness_factor": factor,
        "strand_young_modulus": mat.young_modulus * factor,
        "strand_shear_modulus": mat.G * factor,
        "held_stiffness_ratio": np.asarray(held, dtype=np.float64) / factor if held is not None else np.zeros(0),
    })
    if result.stiffness_ratio is not None:
        arrays["stiffness_ratio"] = np.asarray(result.stiffness_ratio, dtype=np.float64) / factor
    c = result.contacts
    m = 0 if c is None else len(c.strand_a)
    arrays.update({
        "contact_strand_a": np.asarray(c.strand_a, dtype=np.int64) if m else np.zeros(0, np.int64),
        "contact_strand_b": np.asarray(c.strand_b, dtype=np.int64) if m else np.zeros(0, np.int64),
        "contact_s_a": np.asarray(c.s_a, dtype=np.float64) if m else np.zeros(0),
        "contact_s_b": np.asarray(c.s_b, dtype=np.float64) if m else np.zeros(0),
        "contact_points": np.asarray(c.point_a, dtype=np.float64) if m else np.zeros((0, 3)),
        "contact_points_b": np.asarray(c.point_b, dtype=np.float64) if m else np.zeros((0, 3)),
        "contact_normals": np.asarray(c.normal, dtype=np.float64) if m else np.zeros((0, 3)),
        "contact_frames": np.asarray(c.frame, dtype=np.float64) if m else np.zeros((0, 3, 3)),
        "contact_forces": np.asarray(result.forces, dtype=np.float64).reshape(-1, 3) if m else np.zeros((0, 3)),
        "contact_radius": np.array(np.nan if getattr(c, "radius", None) is None else float(c.radius)),
    })
    head = result.head
    arrays["head_vertices"] = np.asarray(head.vertices, dtype=np.float64) if head is not None else np.zeros((0, 3))
    arrays["head_faces"] = np.asarray(head.faces, dtype=np.int64) if head is not None else np.zeros((0, 3), np.int64)
    arrays.update(getattr(result, "extra_arrays", {}) or {})
    return arrays


def _json_default(obj):
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


def write_json(path, data: dict) -> None:
    with atomic_open(path, "w", encoding="utf-8") as f:
        json.dump(data, f, indent=2, default=_json_default)
        f.write("\n")


def write_npz(path, arrays: dict) -> None:
    with atomic_open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def write_result(result, outdir, formats=("npz", "obj", "json"), extra=None) -> list[Path]:
    """Write the requested outputs as one set at ``outdir`` (created if needed); returns the paths.

    ``extra(directory) -> [paths]`` writes more files into the set (``groom invert --format usd``).
    A failure (full disk, interrupt) leaves ``outdir`` as it was; OSError becomes GroomError.
    """
    from . import save_groom

    try:
        with output_set(outdir) as stage:
            written = []
            if "npz" in formats:
                write_npz(stage / "rest.npz", result_arrays(result))
                written.append("rest.npz")
            if "obj" in formats:
                for name, (pts, offsets) in (("rest_shape.obj", result.rest_shape()),
                                             ("fitted.obj", result.fitted_shape())):
                    save_groom(Groom(pts, offsets, up=result.groom.up, source=name), stage / name)
                    written.append(name)
            if "json" in formats:
                write_json(stage / "report.json", result.report)
                written.append("report.json")
            if extra is not None:
                written += [Path(p).relative_to(stage) for p in extra(stage)]
    except OSError as exc:
        raise GroomError(f"{outdir}: cannot write the outputs: {exc.strerror or exc}; "
                         "the directory is unchanged") from exc
    return [Path(outdir) / name for name in written]
