"""An inversion result's output directory: written here (rest.npz, rest_shape.obj, fitted.obj,
report.json) and read back here; the only module that knows rest.npz's keys and their defaults.

Writing: the directory is one atomic set (io/outset.py): all files are written into a staging
directory and swapped in together, so the directory holds the old complete set or the new one, never
a mix, and no stale output of an earlier run.  The schema of rest.npz is documented in
docs/outputs.md.

Reading: :func:`load_arrays` gives the checked rest.npz arrays of a result (an ``InversionResult``, an
output directory, its rest.npz or the arrays themselves); :func:`read_result` the typed view of them
(:class:`SavedResult`: helices, rest curvatures, material, gravity, head, per-strand stiffness,
contact forces, report.json), which ``groom check`` / ``groom simulate``, the Python API and the
exporters (io/fields.py) use.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ..groom import Groom, GroomError
from ..material import Material
from ..rods import clothoid as cl
from ..rods import superhelix as sh
from .atomic import atomic_open
from .obj import write_obj
from .outset import output_set
from .result_check import check_result_arrays, read_report

NPZ_SCHEMA_VERSION = 1
REQUIRED = ("strand_offsets", "element_lengths", "root_positions", "root_frames", "curvatures",
            "rest_curvatures")
#: rest.npz "model": absent in results written before issue 20 (Super-Helices)
MODELS = ("superhelix", "clothoid")
#: the nodal data of a Super Space Clothoid result (model "clothoid"): node offsets (S + 1,), the fitted and the
#: rest Darboux vectors at the nodes (n_nodes, 3); its "curvatures" / "rest_curvatures" are element means
CLOTHOID_KEYS = ("clothoid_node_offsets", "clothoid_curvatures", "clothoid_rest_curvatures")


class ModelError(GroomError):
    """A result of a rod model the caller cannot take (a Super Space Clothoid where a Super-Helix is needed)."""


def _element_means(rod, nodal: np.ndarray) -> np.ndarray:
    """(E, 3) the mean of the nodal Darboux vector over each element ((q_j + q_{j+1}) / 2, flat)."""
    return (0.5 * (nodal[:, :-1] + nodal[:, 1:]))[rod.element_mask]


def input_strand_index(n_strands: int, repairs: dict | None) -> np.ndarray:
    """For each output strand the index of its strand in the input file: the identity, except after
    ``--repair`` dropped strands (io.validate: ``repairs["dropped_strands"]``, input indices)."""
    dropped = np.asarray((repairs or {}).get("dropped_strands", []), dtype=np.int64)
    return np.delete(np.arange(n_strands + len(dropped), dtype=np.int64), dropped)


def result_arrays(result) -> dict:
    """The arrays of rest.npz (flat, unpadded, SI units).  A Super Space Clothoid result (model "clothoid") also
    carries its nodal data (CLOTHOID_KEYS); its per-element "curvatures" / "rest_curvatures" are the element means
    of the nodal values (a Super-Helix reader that ignores "model" would get an approximation, not the
    equilibrium: :meth:`SavedResult.helix` refuses such a result)."""
    helix = result.helix
    mat = result.material
    clothoid = isinstance(helix, cl.SuperClothoid)
    if clothoid:
        flat_offsets = np.concatenate([[0], np.cumsum(helix.n_elements)]).astype(np.int64)
        curv, rest = _element_means(helix, helix.curvatures), _element_means(helix, result.rest_curvatures)
    else:
        flat_offsets = helix.flat_offsets()
        curv, rest = helix.to_flat(helix.curvatures), helix.to_flat(result.rest_curvatures)
    arrays = {
        "schema_version": np.array(NPZ_SCHEMA_VERSION),
        "model": np.array("clothoid" if clothoid else "superhelix"),
        "strand_offsets": flat_offsets,
        "element_lengths": helix.lengths[helix.element_mask],
        "root_positions": helix.root_positions,
        "root_frames": helix.root_frames,
        "curvatures": curv,
        "rest_curvatures": rest,
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
    arrays["input_strand"] = input_strand_index(helix.n_strands, result.groom.metadata.get("repairs"))
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
    if clothoid:
        arrays.update({"clothoid_node_offsets": helix.flat_offsets(),
                       "clothoid_curvatures": helix.to_flat(helix.curvatures),
                       "clothoid_rest_curvatures": helix.to_flat(result.rest_curvatures)})
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
    try:
        with output_set(outdir) as stage:
            written = []
            if "npz" in formats:
                write_npz(stage / "rest.npz", result_arrays(result))
                written.append("rest.npz")
            if "obj" in formats:
                for name, (pts, offsets) in (("rest_shape.obj", result.rest_shape()),
                                             ("fitted.obj", result.fitted_shape())):
                    write_obj(Groom(pts, offsets, up=result.groom.up, source=name), stage / name)
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


# --------------------------------------------------------------------------------------- reading
def load_arrays(source) -> dict:
    """The rest.npz arrays of ``source`` (result object, directory, rest.npz path or dict)."""
    if isinstance(source, dict):
        arrays = source
    elif hasattr(source, "helix") and hasattr(source, "rest_curvatures"):
        arrays = result_arrays(source)
        arrays["source"] = np.array(str(source.groom.source))
    else:
        path = Path(source)
        if path.is_dir():
            path = path / "rest.npz"
        if not path.is_file():
            raise GroomError(f"{path}: no such file (give an output directory of 'groom invert' or its rest.npz)")
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile) as exc:
            raise GroomError(f"{path}: not a readable rest.npz: {exc}") from exc
        arrays["source"] = np.array(str(path))
        missing = [k for k in REQUIRED if k not in arrays]
        if missing:
            raise GroomError(f"{path}: lacks {', '.join(missing)}: not a groomtool result")
        check_result_arrays(arrays, str(path))
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise GroomError(f"result arrays lack {', '.join(missing)}: not a groomtool result")
    return arrays


def up_axis(arrays: dict) -> str:
    """"y" or "z": the axis opposite to gravity (rest.npz ``gravity``), "y" when unknown."""
    g = np.asarray(arrays.get("gravity", np.zeros(3)), dtype=np.float64).reshape(-1)
    if g.size != 3 or not np.any(g):
        return "y"
    return "z" if int(np.argmax(np.abs(g))) == 2 else "y"


def result_model(arrays: dict) -> str:
    """rest.npz's rod model: "superhelix" (also when absent: results written before issue 20) or "clothoid"."""
    model = str(np.asarray(arrays.get("model", "superhelix")))
    if model not in MODELS:
        raise GroomError(f"{arrays.get('source', 'rest.npz')}: unknown rod model {model!r} (known: {', '.join(MODELS)})")
    return model


def result_clothoid(arrays: dict, rest: bool = False) -> cl.SuperClothoid:
    """The fitted Super Space Clothoids of a model "clothoid" result (``rest=True``: with the nodal rest
    curvatures), padded."""
    if result_model(arrays) != "clothoid":
        raise ModelError(f"{arrays.get('source', 'rest.npz')}: a Super-Helix result, not a Super Space Clothoid one")
    missing = [k for k in CLOTHOID_KEYS if k not in arrays]
    if missing:
        raise GroomError(f"{arrays.get('source', 'rest.npz')}: a clothoid result without {', '.join(missing)}")
    offsets = np.asarray(arrays["strand_offsets"], dtype=np.int64)
    counts = np.diff(offsets)
    nodes = np.asarray(arrays["clothoid_node_offsets"], dtype=np.int64)
    q_flat = np.asarray(arrays["clothoid_rest_curvatures" if rest else "clothoid_curvatures"],
                        dtype=np.float64).reshape(-1, 3)
    if nodes.shape != offsets.shape or np.any(np.diff(nodes) != counts + 1) or nodes[-1] != len(q_flat):
        raise GroomError(f"{arrays.get('source', 'rest.npz')}: clothoid_node_offsets do not match the elements")
    if not np.all(np.isfinite(q_flat)):
        raise GroomError(f"{arrays.get('source', 'rest.npz')}: non-finite clothoid curvatures")
    n_max = int(counts.max()) if len(counts) else 0
    mask = np.arange(n_max)[None, :] < counts[:, None]
    lengths = np.zeros(mask.shape)
    lengths[mask] = arrays["element_lengths"]
    q = np.zeros((len(counts), n_max + 1, 3))
    q[np.arange(n_max + 1)[None, :] <= counts[:, None]] = q_flat
    return cl.SuperClothoid(arrays["root_positions"], arrays["root_frames"], lengths, q, counts)


def result_helix(arrays: dict, rest: bool = False) -> sh.SuperHelix:
    """The fitted Super-Helices (``rest=True``: with the rest curvatures), padded.  A Super Space Clothoid result
    raises :class:`ModelError`: its per-element curvatures are element means, not a Super-Helix equilibrium
    (:func:`result_rod` takes either model; the exporters, the viewer, the simulator and ``groom check`` use it)."""
    if result_model(arrays) == "clothoid":
        raise ModelError(f"{arrays.get('source', 'rest.npz')}: a Super Space Clothoid result (groom invert --model "
                         "clothoid), not Super-Helices; read it with groomtool.io.results.result_rod(...) or "
                         "read_result(...).rod() (docs/clothoid.md)")
    offsets = np.asarray(arrays["strand_offsets"], dtype=np.int64)
    counts = np.diff(offsets)
    n_max = int(counts.max()) if len(counts) else 0
    mask = np.arange(n_max)[None, :] < counts[:, None]
    lengths = np.zeros(mask.shape)
    lengths[mask] = arrays["element_lengths"]
    q = np.zeros(mask.shape + (3,))
    q[mask] = np.asarray(arrays["rest_curvatures" if rest else "curvatures"]).reshape(-1, 3)
    return sh.SuperHelix(arrays["root_positions"], arrays["root_frames"], lengths, q, counts)


def result_rod(arrays: dict, rest: bool = False):
    """The fitted rods of either model, padded (``rest=True``: with the rest curvatures): a
    :class:`~groomtool.rods.superhelix.SuperHelix` or, for a model "clothoid" result, a
    :class:`~groomtool.rods.clothoid.SuperClothoid` (nodal curvatures (S, N + 1, 3))."""
    return result_clothoid(arrays, rest) if result_model(arrays) == "clothoid" else result_helix(arrays, rest)


def rod_module(rod):
    """The kinematics module of a rod (:mod:`groomtool.rods.clothoid` or :mod:`groomtool.rods.superhelix`): both
    have ``kinematics``, ``evaluate``, ``evaluate_positions``, ``sample`` and ``locate`` with the same signatures."""
    return cl if isinstance(rod, cl.SuperClothoid) else sh


def head_mesh(arrays: dict):
    """(vertices (n, 3), faces (f, 3)) of the head stored in the result, or None."""
    v = np.asarray(arrays.get("head_vertices", np.zeros((0, 3))), dtype=np.float64).reshape(-1, 3)
    f = np.asarray(arrays.get("head_faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    return (v, f) if len(v) and len(f) else None


def per_strand_stiffness(arrays: dict, material: Material, n_strands: int):
    """((S, 3) per-unit-length (GJ_s, EI_s, EI_s) or None, stiffness_factor (S,) or None) from rest.npz.

    E_s = strand_young_modulus (else E), G_s = strand_shear_modulus (else G E_s / E); without either
    array but with stiffness_factor: (GJ, EI, EI) x factor_s.  Arrays of the wrong length are an error."""

    def per_strand(name):
        if name not in arrays:
            return None
        x = np.asarray(arrays[name], dtype=np.float64).reshape(-1)
        if x.size != n_strands:
            raise ValueError(f"rest.npz: {name} has {x.size} values for {n_strands} strands")
        if not np.all(np.isfinite(x) & (x > 0)):
            bad = int(np.flatnonzero(~(np.isfinite(x) & (x > 0)))[0])
            raise ValueError(f"rest.npz: {name} of strand {bad} is {x[bad]} (must be positive)")
        return x

    E_s, G_s, factor = (per_strand(n) for n in ("strand_young_modulus", "strand_shear_modulus", "stiffness_factor"))
    I = material.second_moment
    if E_s is None and G_s is None:
        if factor is None:
            return None, None
        return factor[:, None] * np.asarray(material.stiffness_diag)[None, :], factor
    E_s = np.full(n_strands, material.young_modulus) if E_s is None else E_s
    G_s = material.G * E_s / material.young_modulus if G_s is None else G_s
    return np.stack([G_s * 2.0 * I, E_s * I, E_s * I], axis=1), factor


@dataclass
class SavedResult:
    """A result read back (:func:`read_result`): rest.npz's arrays (``arrays``, checked) and
    report.json (``report``, {} when absent), with typed accessors and the defaults of missing keys
    (a rest.npz written before a key existed)."""

    arrays: dict
    report: dict = field(default_factory=dict)

    @property
    def source(self) -> str:
        return str(self.arrays["source"]) if "source" in self.arrays else ""

    def helix(self, rest: bool = False) -> sh.SuperHelix:
        """The fitted Super-Helices, padded (``rest=True``: with the rest curvatures); :class:`ModelError` for a
        Super Space Clothoid result (:meth:`clothoid`)."""
        return result_helix(self.arrays, rest=rest)

    @property
    def model(self) -> str:
        """"superhelix" or "clothoid" (rest.npz "model"; absent: "superhelix")."""
        return result_model(self.arrays)

    def clothoid(self, rest: bool = False) -> cl.SuperClothoid:
        """The fitted Super Space Clothoids of a model "clothoid" result, padded (``rest=True``: nodal rest
        curvatures)."""
        return result_clothoid(self.arrays, rest=rest)

    def rod(self, rest: bool = False):
        """The fitted rods of either model (:meth:`helix` or :meth:`clothoid`)."""
        return self.clothoid(rest) if self.model == "clothoid" else self.helix(rest)

    @property
    def rest_curvatures(self) -> np.ndarray:
        """(S, N, 3) rest curvatures, padded like :meth:`helix` (clothoid: nodal, (S, N + 1, 3), like :meth:`clothoid`)."""
        return self.rod(rest=True).curvatures

    def scalar(self, name: str, default=None):
        """A scalar array of rest.npz as a float, ``default`` when absent."""
        return float(self.arrays[name]) if name in self.arrays else default

    @property
    def gravity(self) -> np.ndarray:
        """(3,) m/s^2; default: the default material's gravity along -y."""
        return np.asarray(self.arrays.get("gravity", [0.0, -Material.gravity, 0.0]), dtype=np.float64).reshape(3)

    @property
    def material(self) -> Material:
        """The scalar material written; the defaults of :class:`Material` for missing entries."""
        d = Material()
        arrays = self.arrays
        return Material(young_modulus=self.scalar("young_modulus", d.young_modulus),
                        radius=self.scalar("radius", d.radius), density=self.scalar("density", d.density),
                        friction=self.scalar("friction", d.friction), shear_modulus=self.scalar("shear_modulus"),
                        gravity=float(np.linalg.norm(self.gravity)) if "gravity" in arrays else d.gravity)

    @property
    def head_mesh(self):
        """(vertices, faces) of the stored head, or None."""
        return head_mesh(self.arrays)

    def head(self):
        """The stored head as a ``trimesh.Trimesh`` (not processed), or None."""
        mesh = self.head_mesh
        if mesh is None:
            return None
        import trimesh

        return trimesh.Trimesh(mesh[0], mesh[1], process=False)

    @property
    def up(self) -> str:
        return up_axis(self.arrays)

    @property
    def stiffness_factor(self) -> np.ndarray | None:
        """(S,) per-strand stiffness factors (docs/stability.md), None when absent or not one per strand."""
        if "stiffness_factor" not in self.arrays:
            return None
        factor = np.asarray(self.arrays["stiffness_factor"], dtype=np.float64)
        n_strands = len(self.arrays["strand_offsets"]) - 1
        return factor if factor.shape == (n_strands,) else None

    def per_strand_stiffness(self, material: Material | None = None):
        """:func:`per_strand_stiffness` of these arrays (``material``: default :attr:`material`)."""
        material = self.material if material is None else material
        return per_strand_stiffness(self.arrays, material, len(self.arrays["strand_offsets"]) - 1)

    @property
    def stiffness_ratio(self) -> np.ndarray | None:
        """(S,) stability ratios (< 1: stable), None when not one per strand."""
        ratio = np.asarray(self.arrays.get("stiffness_ratio", np.zeros(0)), dtype=np.float64)
        return ratio if ratio.size == len(self.arrays["strand_offsets"]) - 1 else None

    @property
    def contacts(self) -> str:
        """The inversion's contact mode (report.json), else "all" with a stored head, "none" without."""
        return self.report.get("parameters", {}).get("contacts", "all" if self.head_mesh is not None else "none")

    @property
    def contact_radius(self) -> float | None:
        """m: rest.npz's contact_radius, else report.json's; None when neither has one."""
        radius = self.scalar("contact_radius")
        if radius is None or not np.isfinite(radius):  # NaN: written without contacts
            radius = self.report.get("contacts", {}).get("radius_m") or self.report.get("parameters", {}).get(
                "contact_radius_m")
        return radius

    @property
    def contact_forces(self):
        """(record, forces (m, 3) N) of the contacts solved, None without: the record has strand_a, s_a,
        strand_b, s_b and frame ((m, 3, 3) rows N, T1, T2; None when not written)."""
        arrays = self.arrays
        if not len(arrays.get("contact_forces", ())):
            return None
        record = SimpleNamespace(strand_a=np.asarray(arrays["contact_strand_a"]), s_a=np.asarray(arrays["contact_s_a"]),
                                 strand_b=np.asarray(arrays["contact_strand_b"]), s_b=np.asarray(arrays["contact_s_b"]),
                                 frame=np.asarray(arrays["contact_frames"], dtype=np.float64).reshape(-1, 3, 3)
                                 if "contact_frames" in arrays else None)
        return record, np.asarray(arrays["contact_forces"], dtype=np.float64).reshape(-1, 3)


def read_result(source) -> SavedResult:
    """The typed view of a result: rest.npz's arrays (:func:`load_arrays`) and, for an output
    directory or its rest.npz, the report.json beside it (when present)."""
    arrays = load_arrays(source)
    report = {}
    if isinstance(source, (str, Path)):
        folder = Path(source) if Path(source).is_dir() else Path(source).parent
        report = read_report(folder)
    return SavedResult(arrays, report)
